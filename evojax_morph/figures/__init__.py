"""Pictures of a search: a run's figures (`plots`), and a saved controller's replay, as a GIF and
an MP4 (`video`)."""
