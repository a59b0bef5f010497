"""A run, by stages: `pipeline` assembles space -> fitness -> MDP -> agent, `driver` runs the
outer loop with its `checkpoints` and `bodylog`, `compile_ahead` lowers later programs on a
second thread, `confirm_stage` measures the best bodies again (`confirm`) and chooses the run's
best, `report` writes the summary with its `plots` and `video`, and `saved_controllers` keeps
trained controllers with their bodies. `python -m evojax_morph.run` starts one (`cli`)."""
