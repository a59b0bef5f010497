"""The solids of capsule bodies, as MuJoCo's compiler computes them: each capsule's frame, mass
and inertia, and each body's mass, centre of mass and principal inertia. Pure JAX, so
`physics.specialise` computes them for any morphology inside jit.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

DENSITY = 1000.0  # kg/m^3, MuJoCo's default geom density


def frame_xz(start: jax.Array, end: jax.Array):
    """Centre, half length, quaternion and rotation matrix of a capsule from `start` to `end`
    in the x-z plane.

    MuJoCo aligns a capsule's z axis with the segment; here that is a rotation about y by
    atan2(dx, dz). A capsule is symmetric about its axis, so this frame and the one MuJoCo's
    compiler picks describe the same solid.
    """
    axis = end - start
    half = 0.5 * jnp.linalg.norm(axis, axis=-1)
    angle = jnp.arctan2(axis[..., 0], axis[..., 2])
    zero, one = jnp.zeros_like(angle), jnp.ones_like(angle)
    quat = jnp.stack([jnp.cos(angle / 2), zero, jnp.sin(angle / 2), zero], -1)
    c, s = jnp.cos(angle), jnp.sin(angle)
    rows = [jnp.stack([c, zero, s], -1), jnp.stack([zero, one, zero], -1)]
    rot = jnp.stack(rows + [jnp.stack([-s, zero, c], -1)], -2)
    return 0.5 * (start + end), half, quat, rot


def frame_3d(start: jax.Array, end: jax.Array):
    """`frame_xz` for a segment anywhere in 3D: the quaternion of the shortest rotation of z
    onto the segment, as MuJoCo's compiler takes for `fromto`."""
    axis = end - start
    length = jnp.linalg.norm(axis, axis=-1, keepdims=True)
    d = axis / length
    quat = jnp.concatenate([1 + d[..., 2:], -d[..., 1:2], d[..., :1], jnp.zeros_like(length)], -1)
    down = 1 + d[..., 2:] < 1e-9  # straight down: half a turn about x
    quat = jnp.where(down, jnp.array([0.0, 1.0, 0.0, 0.0], d.dtype), quat)
    quat = quat / jnp.linalg.norm(quat, axis=-1, keepdims=True)
    return 0.5 * (start + end), 0.5 * length[..., 0], quat, quat_to_mat(quat)


def quat_to_mat(q: jax.Array) -> jax.Array:
    """(..., 4) unit quaternions (w, x, y, z) -> (..., 3, 3) rotation matrices."""
    w, x, y, z = (q[..., i] for i in range(4))
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return jnp.stack([jnp.stack(r, -1) for r in rows], -2)


def mat_to_quat(r: jax.Array) -> jax.Array:
    """(..., 3, 3) rotation matrices -> (..., 4) unit quaternions, from the largest of the four
    candidate components (Shepperd), so no division is near zero."""
    e = lambda i, j: r[..., i, j]  # noqa: E731
    t = [1 + e(0, 0) + e(1, 1) + e(2, 2), 1 + e(0, 0) - e(1, 1) - e(2, 2),
         1 - e(0, 0) + e(1, 1) - e(2, 2), 1 - e(0, 0) - e(1, 1) + e(2, 2)]
    zx, yz, xy = e(2, 1) - e(1, 2), e(0, 2) - e(2, 0), e(1, 0) - e(0, 1)
    sx, sy, sz = e(2, 1) + e(1, 2), e(0, 2) + e(2, 0), e(1, 0) + e(0, 1)
    candidates = jnp.stack([  # each proportional to (w, x, y, z), the k-th component 4 q_k^2
        jnp.stack([t[0], zx, yz, xy], -1), jnp.stack([zx, t[1], sz, sy], -1),
        jnp.stack([yz, sz, t[2], sx], -1), jnp.stack([xy, sy, sx, t[3]], -1)], -2)
    best = jnp.argmax(jnp.stack(t, -1), -1)
    q = jnp.take_along_axis(candidates, best[..., None, None], -2)[..., 0, :]
    q = q / jnp.linalg.norm(q, axis=-1, keepdims=True)
    return q * jnp.where(q[..., :1] < 0, -1.0, 1.0)


def inertia(radius: jax.Array, half: jax.Array):
    """Mass and principal inertia (x, y, z; z along the axis) of a solid capsule of DENSITY."""
    h = 2 * half
    cyl = DENSITY * jnp.pi * radius**2 * h
    caps = DENSITY * 4.0 / 3.0 * jnp.pi * radius**3  # both hemispheres
    axial = cyl * radius**2 / 2 + caps * 2 * radius**2 / 5
    perp = cyl * (3 * radius**2 + h**2) / 12
    perp = perp + caps * (2 * radius**2 / 5 + h**2 / 4 + 3 * h * radius / 8)
    return cyl + caps, jnp.stack([perp, perp, axial], -1)


def _bodies(owner: np.ndarray, mass_g, inertia_g, centre_g, rot_g):
    """Each body's mass, centre of mass and inertia tensor about it: the sum of its capsules'
    tensors moved there (parallel axes).

    Args:
      owner: (B, G) 1 where geom g hangs on body b.
      mass_g, inertia_g, centre_g, rot_g: (G,), (G, 3), (G, 3), (G, 3, 3) per capsule: mass,
        principal inertia, centre and frame.
    """
    mass = owner @ mass_g
    safe = jnp.where(mass > 0, mass, 1.0)
    com = (owner @ (mass_g[:, None] * centre_g)) / safe[:, None]
    tensor_g = jnp.einsum("gij,gj,gkj->gik", rot_g, inertia_g, rot_g)
    offset = centre_g[None] - com[:, None]  # (B, G, 3)
    shift = mass_g[None, :, None, None] * (
        jnp.sum(offset**2, -1)[..., None, None] * jnp.eye(3)
        - offset[..., :, None] * offset[..., None, :]
    )
    tensor = jnp.einsum("bg,gij->bij", owner, tensor_g) + jnp.sum(owner[..., None, None] * shift, 1)
    return mass, com, tensor


def bodies_xz(owner: np.ndarray, mass_g, inertia_g, centre_g, rot_g):
    """Mass (B,), centre of mass (B, 3), principal inertia (B, 3) and its frame (B, 4) of every
    body whose capsules lie in the x-z plane (arguments as `_bodies`).

    Such a tensor has no xy or yz products, so its principal frame is a rotation about y, found
    in closed form.
    """
    mass, com, tensor = _bodies(owner, mass_g, inertia_g, centre_g, rot_g)
    ixx, iyy, izz, ixz = tensor[:, 0, 0], tensor[:, 1, 1], tensor[:, 2, 2], tensor[:, 0, 2]
    phi = 0.5 * jnp.arctan2(2 * ixz, ixx - izz)  # principal axis (cos phi, 0, sin phi)
    c, s = jnp.cos(phi), jnp.sin(phi)
    i_x = c * c * ixx + 2 * c * s * ixz + s * s * izz
    principal = jnp.stack([i_x, iyy, s * s * ixx - 2 * c * s * ixz + c * c * izz], -1)
    zero = jnp.zeros_like(phi)
    iquat = jnp.stack([jnp.cos(phi / 2), zero, -jnp.sin(phi / 2), zero], -1)  # rotation by -phi
    return mass, com, principal, iquat


def bodies_3d(owner: np.ndarray, mass_g, inertia_g, centre_g, rot_g):
    """`bodies_xz` for capsules in any direction: the principal frame by eigh."""
    mass, com, tensor = _bodies(owner, mass_g, inertia_g, centre_g, rot_g)
    principal, axes = jnp.linalg.eigh(tensor)  # columns: the principal axes in the body frame
    axes = axes * jnp.sign(jnp.linalg.det(axes))[:, None, None]  # a rotation, not a reflection
    return mass, com, jnp.maximum(principal, 0.0), mat_to_quat(axes)
