"""The MANO hand model and its parameters as Equinox pytrees.

`ManoModel` holds the arrays of a MANO-format model (our built-in open hand, or a
user's official file) and is data, not weights: pass it beside a network or fit.
`ManoParams` is one hand in one frame. Conventions: docs/architecture.md.
"""

import hashlib

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .constants import MANO_PARENTS, NUM_BETAS, NUM_JOINTS, NUM_POSE_FEATURES


class ManoModel(eqx.Module):
    """Arrays of a MANO-format hand model (metres, model frame).

    Build one with `load_builtin`, `load_mano_pkl` or `ManoModel(...)`; the loaders
    validate everything, so jitted code trusts the fields.
    """

    v_template: Float[Array, "verts 3"]
    """Rest-pose vertices at betas = 0, model frame, metres."""
    shapedirs: Float[Array, "verts 3 betas"]
    """Shape blend shapes: rest offsets per unit beta (metres)."""
    posedirs: Float[Array, "verts 3 135"]
    """Pose corrective blend shapes, linear in vec(R_j - I) of joints 1..15 (row-major)."""
    J_regressor: Float[Array, "16 verts"]
    """Dense regressor from rest (shaped) vertices to the 16 MANO joints."""
    weights: Float[Array, "verts 16"]
    """Linear-blend-skinning weights; rows sum to one."""
    faces: Int[Array, "faces 3"]
    """Triangles, counter-clockwise seen from outside."""
    fingertip_ids: Int[Array, "5"]
    """Vertex ids of the fingertip keypoints (thumb, index, middle, ring, pinky)."""
    hands_components: Float[Array, "45 45"]
    """PCA pose basis; row k is a 45-D pose direction (not necessarily unit, as in MANO)."""
    hands_mean: Float[Array, "45"]
    """Mean hand pose of the PCA space (axis-angle, 15 x 3 flattened)."""
    is_right: Bool[Array, ""]
    """Handedness as data, so right and left models share one compiled graph."""
    left_shapedirs_fixed: Bool[Array, ""]
    """True when the loader negated the x shapedirs of an official left model (smplx#48)."""
    joint_template: Float[Array, "16 3"]
    """`J_regressor @ v_template`, computed at construction (the regressor folded in)."""
    joint_shapedirs: Float[Array, "16 3 betas"]
    """`J_regressor @ shapedirs`, computed at construction."""
    pose_basis: Float[Array, "verts 3 active"]
    """The columns of `posedirs` that are not identically zero (computed at construction;
    all 135 for the official model, fewer for models with local correctives)."""
    pose_feature_ids: tuple[int, ...] = eqx.field(static=True)
    """Which of the 135 pose features `pose_basis` uses."""
    parents: tuple[int, ...] = eqx.field(static=True)
    """Parent of each joint; -1 for the wrist (MANO's tree)."""

    def __init__(
        self,
        *,
        v_template,
        shapedirs,
        posedirs,
        J_regressor,
        weights,
        faces,
        fingertip_ids,
        hands_components,
        hands_mean,
        is_right,
        left_shapedirs_fixed=False,
        parents: tuple[int, ...] = MANO_PARENTS,
    ):
        dtype = jnp.result_type(float)
        self.v_template = jnp.asarray(v_template, dtype)
        self.shapedirs = jnp.asarray(shapedirs, dtype)
        self.posedirs = jnp.asarray(posedirs, dtype)
        self.J_regressor = jnp.asarray(J_regressor, dtype)
        self.weights = jnp.asarray(weights, dtype)
        self.faces = jnp.asarray(faces, jnp.int32)
        self.fingertip_ids = jnp.asarray(fingertip_ids, jnp.int32)
        self.hands_components = jnp.asarray(hands_components, dtype)
        self.hands_mean = jnp.asarray(hands_mean, dtype)
        self.is_right = jnp.asarray(is_right, bool)
        self.left_shapedirs_fixed = jnp.asarray(left_shapedirs_fixed, bool)
        self.parents = tuple(int(p) for p in parents)
        self.joint_template = self.J_regressor @ self.v_template
        self.joint_shapedirs = jnp.einsum("jv,vcb->jcb", self.J_regressor, self.shapedirs)
        self.pose_feature_ids = _active_columns(self.posedirs)
        self.pose_basis = self.posedirs[:, :, jnp.asarray(self.pose_feature_ids, jnp.int32)]

    def __check_init__(self):
        V = self.v_template.shape[0]
        expected = {
            "v_template": (V, 3),
            "shapedirs": (V, 3, self.shapedirs.shape[-1]),
            "posedirs": (V, 3, NUM_POSE_FEATURES),
            "J_regressor": (NUM_JOINTS, V),
            "weights": (V, NUM_JOINTS),
            "fingertip_ids": (5,),
            "hands_components": (45, 45),
            "hands_mean": (45,),
        }
        for name, shape in expected.items():
            if getattr(self, name).shape != shape:
                raise ValueError(f"ManoModel.{name} has shape {getattr(self, name).shape}, expected {shape}")
        if self.faces.ndim != 2 or self.faces.shape[1] != 3:
            raise ValueError(f"ManoModel.faces has shape {self.faces.shape}, expected (F, 3)")
        if len(self.parents) != NUM_JOINTS:
            raise ValueError(f"ManoModel.parents has {len(self.parents)} entries, expected {NUM_JOINTS}")

    def replace(self, **changes) -> "ManoModel":
        """A copy with some source arrays replaced and the derived ones recomputed (use
        this rather than `eqx.tree_at`, which would leave `joint_template` & co. stale)."""
        fields = dict(
            v_template=self.v_template, shapedirs=self.shapedirs, posedirs=self.posedirs,
            J_regressor=self.J_regressor, weights=self.weights, faces=self.faces,
            fingertip_ids=self.fingertip_ids, hands_components=self.hands_components,
            hands_mean=self.hands_mean, is_right=self.is_right,
            left_shapedirs_fixed=self.left_shapedirs_fixed, parents=self.parents,
        )  # fmt: skip
        unknown = set(changes) - set(fields)
        if unknown:
            raise TypeError(f"ManoModel.replace got unknown fields {sorted(unknown)}")
        fields.update(changes)
        return ManoModel(**fields)

    @property
    def num_vertices(self) -> int:
        return self.v_template.shape[0]

    @property
    def num_betas(self) -> int:
        return self.shapedirs.shape[-1]

    @property
    def side(self) -> str:
        """'right' or 'left' (needs a concrete model, not a traced one)."""
        return "right" if bool(self.is_right) else "left"


def _active_columns(posedirs: Array) -> tuple[int, ...]:
    """Indices of the pose features with a non-zero blend shape (all of them when the
    arrays are traced, i.e. when a model is built inside a transformation)."""
    try:
        dense = np.asarray(posedirs)
    except jax.errors.TracerArrayConversionError:
        return tuple(range(NUM_POSE_FEATURES))
    return tuple(int(i) for i in np.flatnonzero(np.any(dense != 0, axis=(0, 1))))


_IDENTITY_ARRAYS = ("v_template", "shapedirs", "posedirs", "J_regressor", "weights", "hands_components", "hands_mean")
"""The float arrays that define what a set of MANO parameters means (faces do not:
they connect the mesh but move no vertex or joint)."""


def model_id(model: ManoModel) -> str:
    """A stable identity of the model that MANO parameters are parameters of.

    `'<side>-<16 hex digits>'`: the side and the start of a sha256 over the arrays that
    define the parameterisation (template, shape and pose blend shapes, joint regressor,
    skinning weights, PCA pose space, kinematic tree, fingertip vertex ids). Floats are
    hashed as float32 (the training precision) with -0.0 made +0.0, so the id does not
    depend on the x64 flag, and a model written with `save_mano_pkl` and read back with
    `load_mano_pkl` keeps its id; two models get the same id if and only if they agree to
    float32 precision. Parameters (betas, pose) of models with different ids must not be
    compared; their joints always can be.

    Needs a concrete model (not one traced inside `jit`).
    """
    digest = hashlib.sha256(b"esther-mano-model-v1")
    try:
        floats = {name: np.asarray(getattr(model, name), np.float32) for name in _IDENTITY_ARRAYS}
        is_right = bool(model.is_right)
        tips = np.asarray(model.fingertip_ids, np.int64)
    except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError) as err:
        raise ValueError("model_id needs a concrete ManoModel; call it outside jit/vmap") from err
    for name, values in floats.items():
        digest.update(f"{name}{values.shape}".encode())
        digest.update(np.ascontiguousarray(values + np.float32(0.0), "<f4").tobytes())  # -0.0 + 0.0 == +0.0
    digest.update(f"fingertip_ids{tips.shape}".encode() + np.ascontiguousarray(tips, "<i8").tobytes())
    digest.update(f"parents{model.parents}".encode())
    side = "right" if is_right else "left"
    return f"{side}-{digest.hexdigest()[:16]}"


class ManoParams(eqx.Module):
    """One hand: pose, shape and metric wrist (docs/architecture.md, "ManoParams").

    Leading batch axes are allowed (e.g. a (T,) sequence); the kinematics take one
    hand, so `jax.vmap` over them.
    """

    global_orient: Float[Array, "*batch 3"]
    """Axis-angle of the wrist in the output frame (radians)."""
    hand_pose: Float[Array, "*batch 15 3"]
    """Axis-angle per MANO joint 1..15, absolute (the flat hand is all zeros)."""
    betas: Float[Array, "*batch 10"]
    """Shape coefficients (unit-variance directions)."""
    transl: Float[Array, "*batch 3"]
    """The wrist joint's position in the output frame (metres); not smplx's offset."""

    @classmethod
    def zeros(cls, num_betas: int = NUM_BETAS, dtype=None) -> "ManoParams":
        """The flat, mean-shape hand with its wrist at the origin."""
        dtype = dtype or jnp.result_type(float)
        return cls(
            global_orient=jnp.zeros(3, dtype),
            hand_pose=jnp.zeros((15, 3), dtype),
            betas=jnp.zeros(num_betas, dtype),
            transl=jnp.zeros(3, dtype),
        )


class ManoOutput(eqx.Module):
    """Result of `forward` for one hand, in the output frame (metres)."""

    vertices: Float[Array, "verts 3"]
    """Posed mesh vertices."""
    joints: Float[Array, "21 3"]
    """The 21 keypoints in MediaPipe/OpenPose order (constants.KEYPOINT_NAMES)."""
    transforms: Float[Array, "16 4 4"]
    """`T_out_joint` of each MANO joint: its posed frame (rest axes rotated) in the output frame."""
