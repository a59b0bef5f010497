"""A run of the command line, by stages: its pipeline (space -> fitness -> MDP -> agent), the driver's loop
with checkpoints and the body log, compile-ahead, confirming the best bodies, the report (plots, videos)
and the saved controllers. `python -m evojax_morph.run` starts one (`cli`).
"""
