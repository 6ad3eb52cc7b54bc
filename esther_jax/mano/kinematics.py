"""MANO forward kinematics: blend shapes, the kinematic chain, linear blend skinning.

Staged as in brentyi/egoallo: `with_shape` (betas -> rest vertices and joints) then
`with_pose` (rotations -> joint frames), then skinning. The joint regressor is folded
into the shape basis at model construction, so no call regresses joints from 778+
vertices. `forward_joints` skins only the five fingertip vertices and is exact
against `forward` (same blend shapes, same transforms); `joints_jacobian` is its
Jacobian in closed form, which fits use as its forward-mode derivative.

All 3x3 products are broadcast multiply-adds (`_math.matmul3`): tiny batched
`dot_general`s are slow on XLA:CPU.
"""

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._math import apply3, chunked, matmul3
from ..rotations import axis_angle_left_jacobian, axis_angle_to_matrix, skew
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
    return _forward(model, _check_params(model, params, check_finite))


# The forward functions' bodies are compiled programs (`eqx.filter_jit`, inlined when
# traced): called eagerly (data generation, notebooks, checks), the kinematic chain's small
# operations would each be compiled on their own for every new shape.
@eqx.filter_jit
def _forward(model: ManoModel, params: ManoParams) -> ManoOutput:
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
    return _forward_rotations(model, local, betas, transl)


@eqx.filter_jit
def _forward_rotations(model: ManoModel, local: Float[Array, "16 3 3"], betas: Float[Array, "betas"], transl: Float[Array, "3"]) -> ManoOutput:
    shaped = with_shape(model, betas)
    return _posed_output(model, shaped, with_rotations(model, shaped, local, transl))


def _posed_output(model: ManoModel, shaped: ShapedHand, posed: PosedHand) -> ManoOutput:
    vertices = _skin(model, posed, shaped, _rest_vertices(model, None, shaped, posed), model.weights)
    tips = vertices[model.fingertip_ids]
    return ManoOutput(vertices=vertices, joints=_keypoints(posed, tips), transforms=_homogeneous(posed))


def forward_joints(
    model: ManoModel, params: ManoParams, *, check_finite: bool = True, analytic_jvp: bool = False
) -> Float[Array, "21 3"]:
    """The 21 keypoints of one hand, skinning only the five fingertip vertices.

    Exactly `forward(model, params).joints` at a fraction of the cost (what fits use).
    `check_finite=False` skips the run-time NaN check, for solvers whose inputs were
    validated once at their edge.
    `analytic_jvp=True` gives forward-mode derivatives in the parameters (`jax.jvp`,
    `jax.jacfwd`) from `joints_jacobian` instead of pushing every tangent through the
    kinematic chain: what least-squares fits want (the keypoints' Jacobian about 4x
    faster at 64 hands, benchmarks/fk.py). Reverse mode then transposes that Jacobian and is about 2x
    slower than plain autodiff, hence off by default. Derivatives in the model's
    arrays always take plain autodiff.
    """
    return _forward_joints(model, _check_params(model, params, check_finite), analytic_jvp)


@eqx.filter_jit
def _forward_joints(model: ManoModel, params: ManoParams, analytic_jvp: bool) -> Float[Array, "21 3"]:
    return (_joints if analytic_jvp else _joints_autodiff)(model, params)


def _joints_autodiff(model: ManoModel, params: ManoParams) -> Float[Array, "21 3"]:
    shaped = with_shape(model, params.betas)
    posed = with_pose(model, shaped, params)
    ids = model.fingertip_ids
    tips = _skin(model, posed, shaped, _rest_vertices(model, ids, shaped, posed), model.weights[ids])
    return _keypoints(posed, tips)


_joints = jax.custom_jvp(_joints_autodiff)


class JointsJacobian(eqx.Module):
    """Derivatives of the 21 keypoints (metres) in the parameters of one hand."""

    pose: Float[Array, "21 3 16 3"]
    """In the axis-angle of the 16 joints (row 0 the global orientation), per radian."""
    betas: Float[Array, "21 3 betas"]
    """In the shape coefficients (as many as `params.betas` has)."""
    transl: Float[Array, "21 3 3"]
    """In the wrist translation."""


def _ancestry(parents: tuple[int, ...]) -> np.ndarray:
    """`A[k, j] = 1` where joint j is joint k or one of its ancestors (static)."""
    A = np.eye(len(parents))
    for k in range(len(parents)):
        j = parents[k]
        while j >= 0:
            A[k, j] = 1.0
            j = parents[j]
    return A


def _cross_columns(u: Float[Array, "*batch 3 c"], v: Float[Array, "*batch 3"]) -> Float[Array, "*batch 3 c"]:
    """`u[..., :, c] x v` for every column c."""
    v = v[..., :, None]
    return jnp.stack(
        [u[..., 1, :] * v[..., 2, :] - u[..., 2, :] * v[..., 1, :],
         u[..., 2, :] * v[..., 0, :] - u[..., 0, :] * v[..., 2, :],
         u[..., 0, :] * v[..., 1, :] - u[..., 1, :] * v[..., 0, :]], axis=-2)  # fmt: skip


def joints_jacobian(model: ManoModel, params: ManoParams) -> JointsJacobian:
    """The analytic Jacobian of `forward_joints` in the parameters of one hand.

    A change `dtheta_j` of joint j's axis-angle turns everything below j about the
    world axis `omega_j = R_parent(j) J_l(theta_j) dtheta_j` (`J_l` the left Jacobian
    of SO(3), `rotations.axis_angle_left_jacobian`), so a joint k under
    j moves by `omega_j x (X_k - X_j)`; a fingertip blends that motion of its skinning
    transforms (weights w_k) and adds its pose-corrective offset, rotated by the blended
    rotation. A change of betas moves the rest bones (rotated into the world by their
    parents) and the fingertips' rest vertices; the translation moves everything.
    Equal to `jax.jacfwd(forward_joints)` to float precision (tested);
    `forward_joints(..., analytic_jvp=True)` takes its forward-mode derivatives from it.
    """
    return forward_joints_with_jacobian(model, params, check_finite=False)[1]


def forward_joints_with_jacobian(model: ManoModel, params: ManoParams, *, check_finite: bool = True) -> tuple[Float[Array, "21 3"], JointsJacobian]:
    """`forward_joints` and `joints_jacobian` from one pass of the kinematics (what a
    least-squares fit with a closed-form Jacobian wants)."""
    params = _check_params(model, params, check_finite)
    return _joints_and_jacobian(model, params)


def _joints_and_jacobian(model: ManoModel, params: ManoParams) -> tuple[Float[Array, "21 3"], JointsJacobian]:
    """The keypoints and their `joints_jacobian` from one pass of the kinematics."""
    betas = _pad_betas(model, params.betas)
    shaped = with_shape(model, betas)
    pose = jnp.concatenate([params.global_orient[None], params.hand_pose], axis=0)
    local = axis_angle_to_matrix(pose)
    posed = with_rotations(model, shaped, local, params.transl)
    R, X = posed.rotations, posed.translations
    parents = np.asarray(model.parents)
    parent = np.where(parents < 0, 0, parents)
    eye = jnp.eye(3, dtype=R.dtype)
    R_parent = jnp.where((parents < 0)[:, None, None], eye[None], R[parent])  # (16, 3, 3)
    A = jnp.asarray(_ancestry(model.parents), R.dtype)

    # world rotation axis per unit of each axis-angle component: E[j, :, c]
    J_left = axis_angle_left_jacobian(pose)  # (16, 3, 3): d local = [J_left d pose]x local
    E = matmul3(R_parent, J_left)

    # joints: d X_k / d pose_j = A[k, j] E_j[:, c] x (X_k - X_j)
    lever = X[:, None, :] - X[None, :, :]  # (k, j, 3)
    joints_pose = (_cross_columns(jnp.broadcast_to(E[None], (16, 16, 3, 3)), lever) * A[:, :, None, None]).transpose(0, 2, 1, 3)
    # fingertips: blend of their skinning transforms k (weights W), about each joint j
    ids = model.fingertip_ids
    W = model.weights[ids]  # (5, 16)
    rest = _rest_vertices(model, ids, shaped, posed)  # (5, 3)
    P = apply3(jnp.broadcast_to(R, (5, 16, 3, 3)), rest[:, None, :] - shaped.joints[None]) + X[None]  # (5, k, 3): each transform's image of the tip
    WA = W @ A  # (5, j): weight of the transforms below j
    M = jnp.einsum("ik,kj,ika->ija", W, A, P) - WA[..., None] * X[None]  # (5, j, 3)
    tips_pose = _cross_columns(jnp.broadcast_to(E[None], (5, 16, 3, 3)), M).transpose(0, 2, 1, 3)  # (5, 3, j, 3)
    R_blend = jnp.einsum("ik,kab->iab", W, R)  # (5, 3, 3)
    if model.pose_feature_ids:
        basis = jnp.zeros((5, 3, 135), R.dtype).at[:, :, jnp.asarray(model.pose_feature_ids)].set(model.pose_basis[ids])
        turn = skew(jnp.swapaxes(J_left[1:], 1, 2))  # (15, c, 3, 3)
        d_local = matmul3(turn, jnp.broadcast_to(local[1:, None], turn.shape))  # d local[j] / d pose[j, c]
        d_rest = jnp.einsum("iajm,jcm->iajc", basis.reshape(5, 3, 15, 9), d_local.reshape(15, 3, 9))
        corrective = jnp.einsum("iab,ibjc->iajc", R_blend, d_rest)
        tips_pose = tips_pose + jnp.concatenate([jnp.zeros((5, 3, 1, 3), R.dtype), corrective], axis=2)

    # betas: rest bones rotated by their parents, summed down the chain
    k = params.betas.shape[0]
    S = model.joint_shapedirs[..., :k]  # (16, 3, k)
    bone = jnp.where((parents < 0)[:, None, None], 0.0, S - S[parent])
    joints_betas = jnp.einsum("kj,jab->kab", A, matmul3(R_parent, bone))
    tips_betas = (
        matmul3(R_blend, model.shapedirs[ids][..., :k])
        - jnp.einsum("ik,kab->iab", W, matmul3(R, S))
        + jnp.einsum("ik,kab->iab", W, joints_betas)
    )
    tips_transl = jnp.sum(W, axis=1)[:, None, None] * eye[None]
    order = jnp.asarray(KEYPOINT_FROM_MANO)
    tips = _skin(model, posed, shaped, rest, W)  # = sum_k W_ik P_ik, in the order `forward_joints` sums
    return _keypoints(posed, tips), JointsJacobian(
        pose=jnp.concatenate([joints_pose, tips_pose], axis=0)[order],
        betas=jnp.concatenate([joints_betas, tips_betas], axis=0)[order],
        transl=jnp.concatenate([jnp.broadcast_to(eye, (16, 3, 3)), tips_transl], axis=0)[order],
    )


def _instantiate(tangent):
    """A tangent as an array (`symbolic_zeros` rules receive `SymbolicZero`s)."""
    if isinstance(tangent, jax.custom_derivatives.SymbolicZero):
        return jnp.zeros(tangent.shape, tangent.dtype)
    return tangent


@functools.partial(_joints.defjvp, symbolic_zeros=True)
def _joints_jvp(primals, tangents):
    model, params = primals
    d_model, d_params = tangents
    if not all(isinstance(t, jax.custom_derivatives.SymbolicZero) for t in jax.tree.leaves(d_model)):
        return jax.jvp(_joints_autodiff, primals, jax.tree.map(_instantiate, tangents))
    joints, jac = _joints_and_jacobian(model, params)
    d = jax.tree.map(_instantiate, d_params)
    d_pose = jnp.concatenate([d.global_orient[None], d.hand_pose], axis=0)
    return joints, (
        jnp.einsum("kajc,jc->ka", jac.pose, d_pose)
        + jnp.einsum("kab,b->ka", jac.betas, d.betas)
        + jnp.einsum("kab,b->ka", jac.transl, d.transl)
    )


def _homogeneous(posed: PosedHand) -> Float[Array, "16 4 4"]:
    top = jnp.concatenate([posed.rotations, posed.translations[:, :, None]], axis=2)
    bottom = jnp.broadcast_to(jnp.asarray([0.0, 0.0, 0.0, 1.0], top.dtype), (16, 1, 4))
    return jnp.concatenate([top, bottom], axis=1)


@eqx.filter_jit
def rest_joints(model: ManoModel, betas: Float[Array, "betas"]) -> Float[Array, "16 3"]:
    """Rest-pose MANO joints `J(beta)` in the model frame (smplx's root pivot is row 0)."""
    return with_shape(model, betas).joints


def forward_batch(model: ManoModel, params: ManoParams, *, chunk: int = 64) -> ManoOutput:
    """`jax.vmap(forward)` over a leading batch axis of `params`, with a kernel made for
    batches.

    Up to `_VMAP_BATCH` hands this is `jax.vmap(forward)` itself. Larger batches run in
    blocks of `chunk` hands through `lax.map` (which keeps the per-vertex intermediates in
    cache), each block as batched products laid out for XLA:CPU: the shape and pose blend
    shapes as one matrix product over a basis of both (prepared once per call), and the
    skinning with the coordinates outermost and the vertices innermost (the blended 3x4
    transforms as one product `A^T W^T`, applied as contiguous multiply-adds). Same values
    as `vmap(forward)` to float rounding (the blend shapes are summed in another order).
    On a 2-core CPU about 2x the throughput of the per-hand kernel in chunks (what this
    was before) at B >= 64, 5.1-5.4x smplx's at B = 1024 where `jit(vmap(forward))`
    reaches 1.2-1.5x (benchmarks/fk.py). Concrete parameters are checked for NaN here, traced ones
    once per call at run time.
    """
    batch = params.transl.shape[0]
    if batch <= _VMAP_BATCH:
        _check_finite_eagerly(params)
        return jax.vmap(forward, in_axes=(None, 0))(model, params)
    return _forward_batch(model, _check_batch(model, params), chunk)


@eqx.filter_jit
def _forward_batch(model: ManoModel, params: ManoParams, chunk: int) -> ManoOutput:
    basis = _blend_basis(model)

    def block(params: ManoParams) -> ManoOutput:
        shaped, posed = jax.vmap(_shaped_and_posed, in_axes=(None, 0))(model, params)
        vertices = _skin_batch(model, basis, shaped, posed)

        def output(vertices: Float[Array, "verts 3"], posed: PosedHand) -> ManoOutput:  # one hand (ManoOutput's fields are typed so)
            return ManoOutput(vertices=vertices, joints=_keypoints(posed, vertices[model.fingertip_ids]), transforms=_homogeneous(posed))

        return jax.vmap(output)(vertices, posed)

    return chunked(block, params, chunk)


_VMAP_BATCH = 32
"""Batches up to this size go through `jax.vmap(forward)`: below it, preparing the batch
kernel's blend basis (a copy of the model's blend shapes) costs more than it saves."""


def _shaped_and_posed(model: ManoModel, params: ManoParams) -> tuple[ShapedHand, PosedHand]:
    shaped = with_shape(model, params.betas)
    return shaped, with_pose(model, shaped, params)


def _check_batch(model: ManoModel, params: ManoParams) -> ManoParams:
    """`_check_params` for a batch (leading axis), the finiteness check once for all."""
    batch = params.transl.shape[0]
    for name in ("global_orient", "hand_pose", "betas", "transl"):
        if getattr(params, name).shape[:1] != (batch,):
            raise ValueError(f"ManoParams.{name} has shape {getattr(params, name).shape}, expected a leading batch axis of {batch}")
    jax.eval_shape(lambda p: jax.vmap(_check_params, in_axes=(None, 0, None))(model, p, False), params)
    if _check_finite_eagerly(params):
        return params
    finite = jnp.all(jnp.asarray([jnp.all(jnp.isfinite(leaf)) for leaf in jax.tree_util.tree_leaves(params)]))
    return eqx.error_if(params, ~finite, "ManoParams contains NaN or infinite values")


def _blend_basis(model: ManoModel) -> Float[Array, "coefficients coordinates_by_verts"]:
    """The shape and pose blend shapes as one matrix, coordinates outer and vertices inner:
    row k is blend shape k (betas first, then the active pose features) as (3, V)."""
    basis = jnp.concatenate([model.shapedirs, model.pose_basis], axis=-1) if model.pose_feature_ids else model.shapedirs
    return basis.transpose(2, 1, 0).reshape(basis.shape[-1], -1)


def _skin_batch(model: ManoModel, basis, shaped: ShapedHand, posed: PosedHand) -> Float[Array, "n verts 3"]:
    """Vertices of a block of hands (leading axis n): `_rest_vertices` then `_skin`, as
    batched products in the (n, coordinate, vertex) layout."""
    n, V = posed.rotations.shape[0], model.num_vertices
    coefficients = shaped.betas
    if model.pose_feature_ids:
        coefficients = jnp.concatenate([coefficients, jax.vmap(_pose_features, in_axes=(None, 0))(model, posed)], axis=1)
    rest = model.v_template.T[None] + (coefficients @ basis).reshape(n, 3, V)
    offsets = posed.translations - apply3(posed.rotations, shaped.joints)
    A = jnp.concatenate([posed.rotations.reshape(n, 16, 9), offsets], axis=2)  # (n, 16, 12)
    blended = jnp.einsum("njk,vj->nkv", A, model.weights)  # (n, 12, V): row 3c+d of R, then t
    vertices = [
        blended[:, 3 * c] * rest[:, 0] + blended[:, 3 * c + 1] * rest[:, 1] + blended[:, 3 * c + 2] * rest[:, 2] + blended[:, 9 + c]
        for c in range(3)
    ]
    return jnp.stack(vertices, axis=1).transpose(0, 2, 1)  # (n, V, 3)
