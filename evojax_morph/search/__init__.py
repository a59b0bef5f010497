"""A search for bodies: a whole run assembled from its config (`pipeline`), the host's loop
that steps every search, a run's or a study's (`loop`), many agents' runs stepping together
with their children in one fitness call a step (`study`), and a search's best bodies confirmed
by fresh evaluations (`confirm`, `em.confirm`)."""
