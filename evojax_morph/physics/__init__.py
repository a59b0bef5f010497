"""The physics of the bodies: the padded MuJoCo templates, capsules, MJCF, the engines that step a flat batch
of worlds (MJX's JAX engine, MuJoCo Warp), size classes, the renderer's OpenGL and XLA's flags.
"""
