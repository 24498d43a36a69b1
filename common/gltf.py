"""glTF 2.0 binary (.glb) of fitted motion: the MakeHuman surface skinned to our skeleton, animated.

What the file holds (metres, y up, the actor's rest forward +z, as glTF wants):
- 17 joint nodes, one per entry of ``JOINT_NAMES``: a node per body segment at its proximal
  joint (named as in our BVH: Hips, Spine, ..., Neck carrying the head, ...) and a fixed
  ``HeadTop`` leaf, so that every joint of poses.jsonl is a node's world position;
- one skinned mesh: the actor's rest surface (``BodyModel.vertices``, the A-pose the body
  model is built in) with its four largest skin weights per vertex;
- one animation: per frame a rotation for every segment node and the root's translation,
  keyed at the sequence's times (the fitted frames' rate, ``fps``, is kept in the animation's
  ``extras``).

Axes: x_gltf = (x, z, -y) of our z-up fit frame (``TO_GLTF``). Blender's importer turns glTF's
y up into its z up, which makes Blender's world our fit frame again; three.js shows the file as
it is (y up).

The skinning is the body model's own linear blend skinning: in the rest pose every segment
rotation is the identity, so each joint's inverse bind matrix is a translation by minus its rest
position, and a posed vertex is sum_s w_s (R_s (v - rest_s) + origin_s) in both.
"""
from __future__ import annotations

import numpy as np
import pygltflib
from scipy.spatial.transform import Rotation

from common.body import HEAD_TOP_SEGMENT, SEGMENT_PARENTS, BodyModel, local_rotations

# our z-up fit frame (the actor facing -y) -> glTF (y up, the actor facing +z)
TO_GLTF = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
SEGMENT_NODE_NAMES = (
    "Hips", "Spine", "Chest", "Neck",
    "LeftArm", "LeftForeArm", "LeftHand", "RightArm", "RightForeArm", "RightHand",
    "LeftUpLeg", "LeftLeg", "LeftFoot", "RightUpLeg", "RightLeg", "RightFoot",
)
JOINT_NODE_NAMES = SEGMENT_NODE_NAMES + ("HeadTop",)  # node i is common.body.JOINT_NAMES[i]
JOINT_PARENTS = SEGMENT_PARENTS + (HEAD_TOP_SEGMENT,)
INFLUENCES = 4                 # joints per vertex that every glTF viewer (three.js too) skins with
BODY_COLOUR = (0.78, 0.58, 0.45, 1.0)  # linear RGBA of the skin material
ROUGHNESS = 0.8
GLB_ALIGN = 4                  # bytes: glTF accessors start at multiples of their component size

_FLOAT, _USHORT, _UINT, _UBYTE = 5126, 5123, 5125, 5121
_ARRAY, _ELEMENTS = 34962, 34963


def to_gltf(points: np.ndarray) -> np.ndarray:
    """(..., 3) points of our z-up fit frame -> glTF axes (y up), metres."""
    return np.asarray(points, dtype=np.float64) @ TO_GLTF.T


def from_gltf(points: np.ndarray) -> np.ndarray:
    """(..., 3) glTF points -> our z-up fit frame (the inverse of ``to_gltf``)."""
    return np.asarray(points, dtype=np.float64) @ TO_GLTF


def continuous_quaternions(R: np.ndarray) -> np.ndarray:
    """(F, 3, 3) rotations -> (F, 4) unit quaternions (x, y, z, w), each on the same side of
    the 4-sphere as the previous one, so that interpolating between keys takes the short way."""
    q = Rotation.from_matrix(R).as_quat()
    signs = np.sign(np.einsum("fi,fi->f", q[1:], q[:-1]))
    signs[signs == 0] = 1.0
    q[1:] *= np.cumprod(signs)[:, None]
    return q


def vertex_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(V, 3) vertices, (T, 3) triangles -> (V, 3) unit normals (area-weighted, by the winding)."""
    tri = vertices[triangles]
    face = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(n, triangles[:, k], face)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.where(length > 0, n / np.maximum(length, 1e-30), np.array([0.0, 1.0, 0.0]))  # isolated vertices
    return n


def top_weights(skin_weights: np.ndarray, count: int = INFLUENCES) -> tuple[np.ndarray, np.ndarray]:
    """(V, S) weights -> (V, count) joint indices (uint8) and weights (float32) summing to 1.

    The largest ``count`` weights, renormalised (the body model has up to 5 per vertex; the
    fifth holds at most 0.4% of a vertex). Unused slots: joint 0, weight 0, as glTF asks.
    """
    order = np.argsort(-skin_weights, axis=1, kind="stable")[:, :count]
    w = np.take_along_axis(skin_weights, order, axis=1)
    w = w / w.sum(axis=1, keepdims=True)
    joints = np.where(w > 0, order, 0).astype(np.uint8)
    w32 = w.astype(np.float32)
    # float32 sums within glTF's tolerance: the rounding error goes to the largest weight
    w32[:, 0] += np.float32(1.0) - w32.sum(axis=1, dtype=np.float32)
    return joints, w32


class _Blob:
    """The GLB's binary chunk, built one buffer view (and accessor) at a time."""

    def __init__(self):
        self.data = bytearray()
        self.views: list[pygltflib.BufferView] = []
        self.accessors: list[pygltflib.Accessor] = []

    def add(self, array: np.ndarray, kind: str, component: int, target: int | None = None,
            bounds: bool = False) -> int:
        """Appends ``array`` (N, k) or (N,) as an accessor of ``kind`` ("VEC3", ...); its index."""
        array = np.ascontiguousarray(array)
        self.data.extend(b"\0" * (-len(self.data) % GLB_ALIGN))
        self.views.append(pygltflib.BufferView(buffer=0, byteOffset=len(self.data), byteLength=array.nbytes,
                                               target=target))
        self.data.extend(array.tobytes())
        flat = array.reshape(len(array), -1)
        acc = pygltflib.Accessor(bufferView=len(self.views) - 1, componentType=component, count=len(array),
                                 type=kind)
        if bounds:  # POSITION and animation inputs must say their range
            acc.min = [float(v) for v in flat.min(axis=0)]
            acc.max = [float(v) for v in flat.max(axis=0)]
        self.accessors.append(acc)
        return len(self.accessors) - 1


def glb_bytes(model: BodyModel, params: np.ndarray, times: np.ndarray, fps: float) -> bytes:
    """The .glb file of ``model`` moving through params (F, 35) at times (F,) seconds."""
    p = np.atleast_2d(params)
    F = len(p)
    blob = _Blob()

    # mesh: the rest surface, skinned
    verts = to_gltf(model.vertices).astype(np.float32)
    normals = vertex_normals(to_gltf(model.vertices), model.triangles).astype(np.float32)
    joints, weights = top_weights(model.skin_weights)
    position = blob.add(verts, "VEC3", _FLOAT, _ARRAY, bounds=True)
    normal = blob.add(normals, "VEC3", _FLOAT, _ARRAY)
    joint_acc = blob.add(joints, "VEC4", _UBYTE, _ARRAY)
    weight_acc = blob.add(weights, "VEC4", _FLOAT, _ARRAY)
    indices = blob.add(model.triangles.reshape(-1).astype(np.uint32 if len(verts) > 65535 else np.uint16),
                       "SCALAR", _UINT if len(verts) > 65535 else _USHORT, _ELEMENTS)

    # skeleton: rest translations relative to the parent; inverse bind matrices (column-major)
    rest = to_gltf(model.joint_rest)  # (17, 3)
    ibm = np.tile(np.eye(4), (len(JOINT_NODE_NAMES), 1, 1))
    ibm[:, :3, 3] = -rest
    ibm_acc = blob.add(ibm.transpose(0, 2, 1).reshape(-1, 16).astype(np.float32), "MAT4", _FLOAT)

    # animation: segment rotations relative to the parent, the root's translation
    local = local_rotations(model, p)  # (F, 16, 3, 3), our axes
    time_acc = blob.add(np.asarray(times, dtype=np.float32), "SCALAR", _FLOAT, bounds=True)
    samplers, channels = [], []
    root_t = blob.add(to_gltf(p[:, 0:3]).astype(np.float32), "VEC3", _FLOAT)
    samplers.append(pygltflib.AnimationSampler(input=time_acc, output=root_t, interpolation="LINEAR"))
    channels.append(pygltflib.AnimationChannel(sampler=0, target=pygltflib.AnimationChannelTarget(
        node=0, path="translation")))
    for s in range(16):
        q = continuous_quaternions(TO_GLTF @ local[:, s] @ TO_GLTF.T).astype(np.float32)
        samplers.append(pygltflib.AnimationSampler(input=time_acc, output=blob.add(q, "VEC4", _FLOAT),
                                                   interpolation="LINEAR"))
        channels.append(pygltflib.AnimationChannel(sampler=len(samplers) - 1, target=pygltflib.AnimationChannelTarget(
            node=s, path="rotation")))

    nodes = []
    for j, name in enumerate(JOINT_NODE_NAMES):
        parent = JOINT_PARENTS[j]
        t = rest[j] - (rest[parent] if parent >= 0 else 0.0)
        children = [c for c in range(len(JOINT_NODE_NAMES)) if JOINT_PARENTS[c] == j]
        nodes.append(pygltflib.Node(name=name, translation=[float(v) for v in t], children=children or None))
    mesh_node = len(nodes)
    nodes.append(pygltflib.Node(name="Body", mesh=0, skin=0))  # skinned: its own transform is unused

    gltf = pygltflib.GLTF2(
        asset=pygltflib.Asset(version="2.0", generator="silhouette-mocap"),
        scene=0,
        scenes=[pygltflib.Scene(name="fitted motion", nodes=[0, mesh_node])],
        nodes=nodes,
        meshes=[pygltflib.Mesh(name="Body", primitives=[pygltflib.Primitive(
            attributes=pygltflib.Attributes(POSITION=position, NORMAL=normal, JOINTS_0=joint_acc, WEIGHTS_0=weight_acc),
            indices=indices, material=0)])],
        materials=[pygltflib.Material(name="skin", doubleSided=True, pbrMetallicRoughness=pygltflib.PbrMetallicRoughness(
            baseColorFactor=list(BODY_COLOUR), metallicFactor=0.0, roughnessFactor=ROUGHNESS))],
        skins=[pygltflib.Skin(name="Armature", joints=list(range(len(JOINT_NODE_NAMES))), skeleton=0,
                              inverseBindMatrices=ibm_acc)],
        animations=[pygltflib.Animation(name="motion", samplers=samplers, channels=channels,
                                        extras={"fps": float(fps), "frames": F})],
        accessors=blob.accessors,
        bufferViews=blob.views,
        buffers=[pygltflib.Buffer(byteLength=len(blob.data))],
    )
    gltf.set_binary_blob(bytes(blob.data))
    return b"".join(gltf.save_to_bytes())


def write_glb(path, model: BodyModel, params: np.ndarray, times: np.ndarray, fps: float) -> None:
    with open(path, "wb") as fh:
        fh.write(glb_bytes(model, params, times, fps))


# ------------------------------------------------------------------------------- reading

def accessor_array(gltf: pygltflib.GLTF2, index: int) -> np.ndarray:
    """Accessor ``index`` of a loaded GLB -> (count, components) or (count,) numpy array."""
    acc = gltf.accessors[index]
    view = gltf.bufferViews[acc.bufferView]
    dtype = {_FLOAT: np.float32, _USHORT: np.uint16, _UINT: np.uint32, _UBYTE: np.uint8}[acc.componentType]
    width = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}[acc.type]
    start = (view.byteOffset or 0) + (acc.byteOffset or 0)
    data = np.frombuffer(gltf.binary_blob(), dtype=dtype, count=acc.count * width, offset=start)
    return data.reshape(acc.count, width) if width > 1 else data


def node_world_matrices(gltf: pygltflib.GLTF2) -> tuple[np.ndarray, np.ndarray]:
    """A loaded GLB -> times (F,) of its first animation and (F, N, 4, 4) every node's world
    matrix at each key, glTF axes: translations and rotations, animated or static, composed
    from the scene root down, as a glTF viewer does."""
    anim = gltf.animations[0]
    times = accessor_array(gltf, anim.samplers[0].input).astype(np.float64)
    F, N = len(times), len(gltf.nodes)
    T = np.array([n.translation or [0.0, 0.0, 0.0] for n in gltf.nodes], dtype=np.float64)[None].repeat(F, 0)
    Q = np.array([n.rotation or [0.0, 0.0, 0.0, 1.0] for n in gltf.nodes], dtype=np.float64)[None].repeat(F, 0)
    for ch in anim.channels:
        (T if ch.target.path == "translation" else Q)[:, ch.target.node] = \
            accessor_array(gltf, anim.samplers[ch.sampler].output)
    local = np.tile(np.eye(4), (F, N, 1, 1))
    local[:, :, :3, :3] = Rotation.from_quat(Q.reshape(-1, 4)).as_matrix().reshape(F, N, 3, 3)
    local[:, :, :3, 3] = T
    parent = {c: i for i, n in enumerate(gltf.nodes) for c in (n.children or [])}
    world = np.full_like(local, np.nan)

    def resolve(i):
        if np.isnan(world[0, i, 0, 0]):
            world[:, i] = resolve(parent[i]) @ local[:, i] if i in parent else local[:, i]
        return world[:, i]

    for i in range(N):
        resolve(i)
    return times, world


def glb_joint_positions(gltf: pygltflib.GLTF2) -> tuple[np.ndarray, np.ndarray]:
    """A loaded GLB of ours -> times (F,) and (F, 17, 3) joints (nodes found by name) in our
    z-up fit frame, metres."""
    times, world = node_world_matrices(gltf)
    names = [n.name for n in gltf.nodes]
    nodes = [names.index(n) for n in JOINT_NODE_NAMES]
    return times, from_gltf(world[:, nodes][..., :3, 3])


def glb_skinned_vertices(gltf: pygltflib.GLTF2, key: int) -> np.ndarray:
    """(V, 3) the skinned mesh at animation key ``key``, our z-up fit frame (glTF skinning:
    the sum over a vertex's joints of weight x joint world matrix x inverse bind matrix)."""
    _, world = node_world_matrices(gltf)
    prim, skin = gltf.meshes[0].primitives[0], gltf.skins[0]
    ibm = accessor_array(gltf, skin.inverseBindMatrices).reshape(-1, 4, 4).transpose(0, 2, 1)  # column-major
    mats = world[key, skin.joints] @ ibm                                                         # (J, 4, 4)
    v = accessor_array(gltf, prim.attributes.POSITION).astype(np.float64)
    joints = accessor_array(gltf, prim.attributes.JOINTS_0).astype(np.int64)
    weights = accessor_array(gltf, prim.attributes.WEIGHTS_0).astype(np.float64)
    blended = np.einsum("vk,vkij->vij", weights, mats[joints])
    return from_gltf(np.einsum("vij,vj->vi", blended[:, :3, :3], v) + blended[:, :3, 3])
