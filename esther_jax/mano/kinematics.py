"""MANO forward kinematics: blend shapes, the kinematic chain, linear blend skinning.

Staged as in brentyi/egoallo: `with_shape` (betas -> rest vertices and joints) then
`with_pose` (rotations -> joint frames), then skinning. The joint regressor is folded
into the shape basis at model construction, so no call regresses joints from 778+
vertices. `forward_joints` skins only the five fingertip vertices and is exact
against `forward` (same blend shapes, same transforms).

All 3x3 products are broadcast multiply-adds (`_math.matmul3`): tiny batched
`dot_general`s are slow on XLA:CPU.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._math import apply3, chunked, matmul3
from ..rotations import axis_angle_to_matrix
from .constants import KEYPOINT_FROM_MANO
from .model import ManoModel, ManoOutput, ManoParams


class ShapedHand(eqx.Module):
    """Rest geometry of one hand at given betas (model frame, metres)."""

    joints: Float[Array, "16 3"]
    """Rest joints `J(beta) = joint_template + joint_shapedirs @ beta`."""
    betas: Float[Array, "betas"]


class PosedHand(eqx.Module):
    """Joint frames of one posed hand in the output frame."""

    rotations: Float[Array, "16 3 3"]
    """World rotation of each joint frame (output frame from rest axes)."""
    translations: Float[Array, "16 3"]
    """Posed joint positions in the output frame."""
    local_rotations: Float[Array, "16 3 3"]
    """Per-joint local rotations (row 0 is the global orientation)."""


def with_shape(model: ManoModel, betas: Float[Array, "betas"]) -> ShapedHand:
    """Rest joints for `betas` (fewer betas than the model has are zero-padded)."""
    betas = _pad_betas(model, betas)
    joints = model.joint_template + jnp.einsum("jcb,b->jc", model.joint_shapedirs, betas)
    return ShapedHand(joints=joints, betas=betas)


def with_pose(model: ManoModel, shaped: ShapedHand, params: ManoParams) -> PosedHand:
    """Chain the axis-angle pose of `params` down MANO's tree (see `with_rotations`)."""
    pose = jnp.concatenate([params.global_orient[None], params.hand_pose], axis=0)
    return with_rotations(model, shaped, axis_angle_to_matrix(pose), params.transl)


def with_rotations(
    model: ManoModel, shaped: ShapedHand, local: Float[Array, "16 3 3"], transl: Float[Array, "3"]
) -> PosedHand:
    """Chain local joint rotations down MANO's tree; the wrist lands at `transl`.

    `local[0]` is the global orientation, `local[j]` joint j's rotation relative to its
    parent (what a network's 6D head emits). World rotation `R_j = R_parent @ R_local_j`,
    position `t_j = t_parent + R_parent @ (J_j - J_parent)`, root `(R_global, transl)`.
    The tree is static, so the chain runs level by level (root, then the five
    fingers' first, second and third joints) as three batched products.
    """
    parents = model.parents
    levels = _levels(parents)
    rot = [None] * 16
    pos = [None] * 16
    rot[0] = local[0]
    pos[0] = transl
    for level in levels[1:]:
        idx = jnp.asarray(level)
        par = [parents[j] for j in level]
        r_par = jnp.stack([rot[p] for p in par])
        t_par = jnp.stack([pos[p] for p in par])
        bone = shaped.joints[idx] - shaped.joints[jnp.asarray(par)]  # rest offsets from the parents
        r_new = matmul3(r_par, local[idx])
        t_new = t_par + apply3(r_par, bone)
        for k, j in enumerate(level):
            rot[j], pos[j] = r_new[k], t_new[k]
    return PosedHand(rotations=jnp.stack(rot), translations=jnp.stack(pos), local_rotations=local)


def _levels(parents: tuple[int, ...]) -> list[list[int]]:
    """Joints grouped by depth in the tree (static)."""
    depth = []
    for j, p in enumerate(parents):
        depth.append(0 if p < 0 else depth[p] + 1)
    return [[j for j in range(len(parents)) if depth[j] == d] for d in range(max(depth) + 1)]


def _pad_betas(model: ManoModel, betas: Float[Array, "betas"]) -> Float[Array, "model_betas"]:
    n = model.num_betas
    if betas.ndim != 1 or betas.shape[0] > n:
        raise ValueError(f"betas must have shape (k,) with k <= {n}; got {betas.shape}")
    return jnp.pad(betas, (0, n - betas.shape[0]))


def _pose_features(model: ManoModel, posed: PosedHand) -> Float[Array, "active"]:
    """MANO's pose features vec(R_j - I) of joints 1..15 (row-major), restricted to the
    ones the model's corrective blend shapes use."""
    eye = jnp.eye(3, dtype=posed.local_rotations.dtype)
    return (posed.local_rotations[1:] - eye[None]).reshape(135)[jnp.asarray(model.pose_feature_ids, jnp.int32)]


def _skin(
    model: ManoModel,
    posed: PosedHand,
    shaped: ShapedHand,
    rest_vertices: Float[Array, "n 3"],
    weights: Float[Array, "n 16"],
) -> Float[Array, "n 3"]:
    """Linear blend skinning of rest-pose vertices (already shaped and pose-corrected).

    Skinning transform of joint j: `x -> R_j x + (t_j - R_j J_j)`; the blended 3x4
    matrices are `weights @ A` (one plain GEMM), applied with multiply-adds.
    """
    offsets = posed.translations - apply3(posed.rotations, shaped.joints)
    A = jnp.concatenate([posed.rotations.reshape(16, 9), offsets], axis=1)  # (16, 12)
    blended = weights @ A  # (n, 12)
    R = blended[:, :9].reshape(-1, 3, 3)
    return apply3(R, rest_vertices) + blended[:, 9:]


def _rest_vertices(model: ManoModel, vertex_ids, shaped: ShapedHand, posed: PosedHand):
    """Shaped and pose-corrected rest vertices (all when `vertex_ids` is None)."""
    take = (lambda a: a) if vertex_ids is None else (lambda a: a[vertex_ids])
    v = take(model.v_template) + jnp.einsum("vcb,b->vc", take(model.shapedirs), shaped.betas)
    if not model.pose_feature_ids:  # a model without corrective blend shapes
        return v
    basis = take(model.pose_basis)
    return v + (basis.reshape(-1, basis.shape[-1]) @ _pose_features(model, posed)).reshape(-1, 3)


def _keypoints(posed: PosedHand, tips: Float[Array, "5 3"]) -> Float[Array, "21 3"]:
    return jnp.concatenate([posed.translations, tips], axis=0)[jnp.asarray(KEYPOINT_FROM_MANO)]


def _check_finite_eagerly(params: ManoParams) -> bool:
    """Raise a ValueError naming the non-finite fields of concrete parameters; False
    (nothing checked) when they are traced."""
    fields = ("global_orient", "hand_pose", "betas", "transl")
    try:
        concrete = {name: np.asarray(getattr(params, name)) for name in fields}
    except jax.errors.TracerArrayConversionError:
        return False  # traced: checked when the program runs
    bad = [name for name, value in concrete.items() if not np.all(np.isfinite(value))]
    if bad:
        raise ValueError(f"ManoParams contains NaN or infinite values (in {', '.join(bad)})")
    return True


def _check_params(model: ManoModel, params: ManoParams, check_finite: bool) -> ManoParams:
    """Trace-time shape checks and, if asked, a finiteness check: eager (a ValueError
    naming the fields) when the parameters are concrete arrays, else at run time
    (`eqx.error_if`: under `jax.jit` its message comes wrapped in a runtime error,
    `eqx.filter_jit` shows it plainly). The run-time check is a host callback, and
    compiled programs that contain one are not stored in the persistent compilation
    cache, so solvers validate at their edge and pass `check_finite=False`."""
    expected = {"global_orient": (3,), "hand_pose": (15, 3), "transl": (3,)}
    for name, shape in expected.items():
        got = getattr(params, name).shape
        if got != shape:
            raise ValueError(
                f"ManoParams.{name} has shape {got}, expected {shape} for one hand; "
                "for a batch or sequence use jax.vmap(forward, in_axes=(None, 0))"
            )
    if params.betas.ndim != 1 or params.betas.shape[0] > model.num_betas:
        raise ValueError(f"ManoParams.betas has shape {params.betas.shape}, expected (k,) with k <= {model.num_betas}")
    if not check_finite:
        return params
    if _check_finite_eagerly(params):
        return params
    finite = jnp.all(jnp.asarray([jnp.all(jnp.isfinite(leaf)) for leaf in jax.tree_util.tree_leaves(params)]))
    return eqx.error_if(params, ~finite, "ManoParams contains NaN or infinite values")


def forward(model: ManoModel, params: ManoParams, *, check_finite: bool = True) -> ManoOutput:
    """Posed vertices, the 21 keypoints and the 16 joint frames of one hand.

    Args:
        model: a MANO-format model (`load_builtin`, `load_mano_pkl`).
        params: one hand; `transl` is the wrist position in the output frame.
        check_finite: raise on NaN / infinite parameters (see `forward_joints`).
    Returns:
        `ManoOutput` with vertices (V, 3), joints (21, 3), transforms (16, 4, 4), metres.
    """
    params = _check_params(model, params, check_finite)
    shaped = with_shape(model, params.betas)
    return _posed_output(model, shaped, with_pose(model, shaped, params))


def forward_rotations(
    model: ManoModel, local: Float[Array, "16 3 3"], betas: Float[Array, "betas"], transl: Float[Array, "3"]
) -> ManoOutput:
    """`forward` from local joint rotation matrices (row 0 global) instead of axis-angle.

    What a network with rotation-matrix or 6D outputs calls: no log/exp round trip.
    """
    if local.shape != (16, 3, 3) or transl.shape != (3,):
        raise ValueError(f"forward_rotations takes one hand: local (16, 3, 3), transl (3,); got {local.shape}, {transl.shape}")
    shaped = with_shape(model, betas)
    return _posed_output(model, shaped, with_rotations(model, shaped, local, transl))


def _posed_output(model: ManoModel, shaped: ShapedHand, posed: PosedHand) -> ManoOutput:
    vertices = _skin(model, posed, shaped, _rest_vertices(model, None, shaped, posed), model.weights)
    tips = vertices[model.fingertip_ids]
    return ManoOutput(vertices=vertices, joints=_keypoints(posed, tips), transforms=_homogeneous(posed))


def forward_joints(model: ManoModel, params: ManoParams, *, check_finite: bool = True) -> Float[Array, "21 3"]:
    """The 21 keypoints of one hand, skinning only the five fingertip vertices.

    Exactly `forward(model, params).joints` at a fraction of the cost (what fits use).
    `check_finite=False` skips the run-time NaN check, for solvers whose inputs were
    validated once at their edge.
    """
    params = _check_params(model, params, check_finite)
    shaped = with_shape(model, params.betas)
    posed = with_pose(model, shaped, params)
    ids = model.fingertip_ids
    tips = _skin(model, posed, shaped, _rest_vertices(model, ids, shaped, posed), model.weights[ids])
    return _keypoints(posed, tips)


def _homogeneous(posed: PosedHand) -> Float[Array, "16 4 4"]:
    top = jnp.concatenate([posed.rotations, posed.translations[:, :, None]], axis=2)
    bottom = jnp.broadcast_to(jnp.asarray([0.0, 0.0, 0.0, 1.0], top.dtype), (16, 1, 4))
    return jnp.concatenate([top, bottom], axis=1)


def rest_joints(model: ManoModel, betas: Float[Array, "betas"]) -> Float[Array, "16 3"]:
    """Rest-pose MANO joints `J(beta)` in the model frame (smplx's root pivot is row 0)."""
    return with_shape(model, betas).joints


def forward_batch(model: ManoModel, params: ManoParams, *, chunk: int = 32) -> ManoOutput:
    """`jax.vmap(forward)` over a leading batch axis of `params`, run in chunks.

    Large batches go through `lax.map` over blocks of `chunk` hands (32 measured best
    on a 2-core CPU), which keeps the per-vertex intermediates in cache and avoids
    faulting fresh pages: about 2x the throughput of a plain vmap at B >= 1024 on CPU
    (benchmarks/fk.py). Same values; concrete parameters are checked for NaN here.
    """
    _check_finite_eagerly(params)
    return chunked(lambda p: jax.vmap(forward, in_axes=(None, 0))(model, p), params, chunk)
