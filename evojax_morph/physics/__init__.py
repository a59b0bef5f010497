"""The physics of the bodies: one padded MuJoCo template per space (`templates`), the solids of
its capsules (`capsules`), MJCF (`mjcf`), the engines that step a flat batch of worlds (`engines`:
MJX's JAX engine, MuJoCo Warp in `warp`, with `warp_models`, `warp_runtime` and `warp_kernels`),
size classes (`classes`), the renderer's OpenGL (`opengl`) and the XLA flags asked for before
JAX starts (`determinism`)."""
