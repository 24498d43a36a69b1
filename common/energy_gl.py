"""The ``gl`` energy backend: the paper's XOR energy, rendered and counted on the GPU (moderngl).

One call evaluates B candidate poses in all K camera windows with one instanced draw:

- Geometry is uploaded once, per segment; per call only a (B, S, 3, 4) table of world
  transforms (one per pose and drawn segment) goes to the GPU. ``surface="mesh"`` draws the
  rigid MakeHuman segments (each vertex moves with its own segment, as
  ``common.body.rigid_vertices``; a triangle is drawn with the segment most of its vertices
  belong to, ``model.triangle_segment``), back faces culled. ``surface="ellipsoid"`` draws each
  of the cpu backend's ellipsoids as the polygon of its silhouette: seen from a point, an
  ellipsoid's contour generator is a planar ellipse (the rim) whose image is exactly the cpu
  backend's image conic, so the vertex shader places RIM_VERTICES points on the rim (scaled
  to the conic's area) and RIM_VERTICES - 2 triangles cover what the cpu backend covers.
- Tiles: instance i is (pose i // K, camera i % K) and owns one h x w tile of an atlas
  framebuffer. The vertex shader applies the camera (lens distortion included) in the
  camera's window (window pixel (u - x0, v - y0)), moves the result into the instance's tile,
  and clip distances cut it to the tile and to the near plane. Windows of different sizes
  (whole images of cameras of different sizes) share the largest tile; a window's pixels
  beyond its own size are marked static and input in the bit planes, so they count nothing.
- XOR and reduction, the paper's stencil trick turned into a count: every vertex is drawn at
  one depth and the depth test is LESS, so only the first fragment of a pixel survives (early
  fragment tests). It reads the paper's bit planes (``common.packing``: camera k in bit k % 8
  of plane k // 8; for the input silhouettes I and, in the next byte, the pre-rendered static
  mask M) and adds v = 0 where M, +1 where not I, -1 where I to its (pose, camera) counter
  with atomicAdd. So |(R or M) xor I| = |M xor I| + sum of v over R, and only B*K ints come
  back, read once after the whole batch is issued.
"""
from __future__ import annotations

import itertools

import numpy as np

from common.body import PARAM_COUNT, BodyModel, forward_kinematics
from common.energy import MIN_DEPTH_M, EnergySetup, ellipsoid_world, window_pixels
from common.packing import pack_planes
from common.render_gl import NEAR_M, gl_context, gl_renderer_name, is_software_renderer

SURFACES = ("mesh", "ellipsoid")
SEGMENTS = 16
RIM_VERTICES = 16           # polygon corners per ellipsoid silhouette (a multiple of 4)
# an inscribed regular n-gon has area n/2 sin(2 pi/n) r^2: scale it to the ellipse's area
RIM_SCALE = float(np.sqrt(2.0 * np.pi / (RIM_VERTICES * np.sin(2.0 * np.pi / RIM_VERTICES))))
# Tile pixels per draw; larger batches are drawn in chunks. A software renderer runs fastest
# with a scene that stays in cache; a GPU wants big draws.
ATLAS_PIXELS_SOFTWARE = 1 << 18
ATLAS_PIXELS_GPU = 1 << 22
CAMERA_VEC4S = 7            # storage-buffer entries per camera
GL_CLIP_DISTANCES = tuple(0x3000 + i for i in range(5))  # GL_CLIP_DISTANCE0..4 (no moderngl name)


# ----------------------------------------------------------------------------- geometry

def mesh_geometry(model: BodyModel) -> tuple:
    """Rigid segments: vertices (V, 3) relative to their segment's joint, vertex segment (V,),
    triangles (T, 3) counter-clockwise seen from outside, triangle segment (T,)."""
    seg = model.vertex_segment.astype(np.int32)
    return (model.vertices - model.joint_rest[seg], seg, model.triangles.astype(np.int32),
            model.triangle_segment.astype(np.int32))


def polygon_triangles(n: int) -> list:
    """Triangles (counter-clockwise) of a convex n-gon, n a multiple of 4, made by halving arcs:
    a large central quad and ever smaller triangles towards the rim instead of a fan's slivers
    (a software rasterizer pays per block of a triangle's bounding box)."""
    def arc(i, j):
        if j - i < 2:
            return []
        m = (i + j) // 2
        return [(i, m, j % n)] + arc(i, m) + arc(m, j)

    q = [0, n // 4, n // 2, 3 * n // 4]
    return [(q[0], q[1], q[2]), (q[0], q[2], q[3])] + [t for a, b in zip(q, q[1:] + [n]) for t in arc(a, b)]


def rim_geometry() -> tuple:
    """One polygon per segment with vertices (cos t, sin t, 1), placed on the rim by the vertex
    shader. Same outputs as ``mesh_geometry``."""
    t = 2.0 * np.pi * np.arange(RIM_VERTICES) / RIM_VERTICES
    circle = np.stack([np.cos(t), np.sin(t), np.ones_like(t)], axis=1)
    poly = np.array(polygon_triangles(RIM_VERTICES))
    n = RIM_VERTICES
    return (np.tile(circle, (SEGMENTS, 1)), np.repeat(np.arange(SEGMENTS, dtype=np.int32), n),
            np.concatenate([poly + s * n for s in range(SEGMENTS)]).astype(np.int32),
            np.repeat(np.arange(SEGMENTS, dtype=np.int32), len(poly)))


# ------------------------------------------------------------------------------ shaders

VERTEX_SHADER = """#version 450
in vec3 in_pos;             // mesh: vertex relative to its joint; rim: (cos t, sin t, 1)
in int in_seg;
// per (pose, slot), rows of a world map [L | o]: the segment's rotation and origin (mesh), or
// the ellipsoid {o + L u : |u| <= 1} (rim)
layout(std430, binding = 0) readonly buffer Poses { vec4 xf[]; };
// per camera: rows of [R | t]; (fx, skew, cx, fy); (cy, x0, y0, has_dist); (k1, k2, p1, p2);
// (k3, centre)
layout(std430, binding = 1) readonly buffer Cameras { vec4 cams[]; };
uniform int n_cams;
uniform int n_slots;
uniform int seg_slot[16];
uniform int inst_base;      // first (pose, camera) of this chunk in the batch
uniform int tile_cols;
uniform vec2 tile_size;     // (w, h) pixels
uniform vec2 atlas_size;    // pixels
flat out ivec4 tile;        // tile origin x, y; camera; (pose, camera) counter
out float gl_ClipDistance[5];

void main() {
    int g = inst_base + gl_InstanceID;
    int k = g % n_cams;
    int m = ((g / n_cams) * n_slots + seg_slot[in_seg]) * 3;
    vec4 r0 = xf[m], r1 = xf[m + 1], r2 = xf[m + 2];
    int cb = CAMERA_VEC4S * k;
    vec4 q0 = cams[cb], q1 = cams[cb + 1], q2 = cams[cb + 2];
    float drawable = 1.0;
#ifdef RIM
    // the rim: tangent points of the cone from the camera, the circle u . e = 1 on the unit
    // sphere of u-space where the camera sits at e = L^-1 (eye - o); a x b = e / |e| keeps
    // every polygon facing its camera
    mat3 L = transpose(mat3(r0.xyz, r1.xyz, r2.xyz));
    vec3 o = vec3(r0.w, r1.w, r2.w);
    vec3 e = inverse(L) * (cams[cb + 6].yzw - o);
    float n2 = dot(e, e);
    if (n2 <= 1.000001 || dot(q2, vec4(o, 1.0)) <= MIN_DEPTH_M) {
        drawable = -1.0;    // camera inside, or centre too near (as the cpu backend): clipped
        n2 = 2.0;
    }
    vec3 eh = e * inversesqrt(n2);
    vec3 a = normalize(cross(abs(eh.x) < 0.9 ? vec3(1.0, 0.0, 0.0) : vec3(0.0, 1.0, 0.0), eh));
    vec3 b = cross(eh, a) * sign(determinant(L));
    vec3 u = eh * inversesqrt(n2) + RIM_SCALE * sqrt(1.0 - 1.0 / n2) * (in_pos.x * a + in_pos.y * b);
    vec4 w = vec4(o + L * u, 1.0);
#else
    vec4 p = vec4(in_pos, 1.0);
    vec4 w = vec4(dot(r0, p), dot(r1, p), dot(r2, p), 1.0);
#endif
    vec3 c = vec3(dot(q0, w), dot(q1, w), dot(q2, w));
    vec4 c0 = cams[cb + 3], c1 = cams[cb + 4];
    float z = c.z;
    vec2 n = c.xy / max(z, 1e-6);
    if (c1.w > 0.5) {
        vec4 d = cams[cb + 5];
        float k3 = cams[cb + 6].x;
        float r2 = dot(n, n);
        float radial = 1.0 + r2 * (d.x + r2 * (d.y + r2 * k3));
        n = n * radial + vec2(2.0 * d.z * n.x * n.y + d.w * (r2 + 2.0 * n.x * n.x),
                              d.z * (r2 + 2.0 * n.y * n.y) + 2.0 * d.w * n.x * n.y);
    }
    // window pixel, pixel centres at integers
    vec2 local = vec2(c0.x * n.x + c0.y * n.y + c0.z, c0.w * n.y + c1.x) - c1.yz;
    ivec2 origin = ivec2(gl_InstanceID % tile_cols, gl_InstanceID / tile_cols) * ivec2(tile_size);
    vec2 ndc = 2.0 * (local + vec2(origin) + 0.5) / atlas_size - 1.0;
    gl_Position = vec4(ndc * z, 0.0, z);   // one depth for all: the depth test keeps one fragment
    // multiplied by z, linear in clip space: clipping to the tile is exact
    gl_ClipDistance[0] = (local.x + 0.5) * z;
    gl_ClipDistance[1] = (tile_size.x - 0.5 - local.x) * z;
    gl_ClipDistance[2] = (local.y + 0.5) * z;
    gl_ClipDistance[3] = (tile_size.y - 0.5 - local.y) * z;
    gl_ClipDistance[4] = drawable * (z - NEAR_M);
    tile = ivec4(origin, k, g);
}
""".replace("CAMERA_VEC4S", str(CAMERA_VEC4S)).replace("NEAR_M", repr(float(NEAR_M))).replace(
    "MIN_DEPTH_M", repr(float(MIN_DEPTH_M))).replace("RIM_SCALE", repr(RIM_SCALE))

COUNT_SHADER = """#version 450
layout(early_fragment_tests) in;
flat in ivec4 tile;
uniform ivec2 tile_px;      // (w, h)
// per plane k / 8 and pixel: input byte | static mask byte << 8, camera k in bit k % 8
layout(std430, binding = 3) readonly buffer Planes { uint planes[]; };
layout(std430, binding = 2) buffer Counts { int counts[]; };

void main() {
    ivec2 p = ivec2(gl_FragCoord.xy) - tile.xy;
    uint bits = planes[((tile.z >> 3) * tile_px.y + p.y) * tile_px.x + p.x] >> uint(tile.z & 7);
    if ((bits & 0x100u) == 0u)
        atomicAdd(counts[tile.w], (bits & 1u) != 0u ? -1 : 1);
}
"""

COVER_SHADER = """#version 450
out float cover;
void main() { cover = 1.0; }
"""


# ------------------------------------------------------------------------------- energy

# The process has one GL context: programs (per surface) and scratch atlases (per size) are
# shared by all energies and live as long as it; each energy releases its own buffers.
_SHARED = {}
_INSTANCES = itertools.count()


def _shared(key, make):
    if key not in _SHARED:
        _SHARED[key] = make()
    return _SHARED[key]


class GlEnergy:
    """The ``gl`` backend (see the module docstring), with the interface of ``CpuEnergy``.

    surface: "mesh" (rigid MakeHuman segments) or "ellipsoid" (the cpu backend's ellipsoids).
    renderer_name: the OpenGL renderer, e.g. "llvmpipe (LLVM ...)" when rendering in software.
    """

    backend = "gl"

    def __init__(self, model: BodyModel, setup: EnergySetup, surface: str = "mesh"):
        import moderngl

        self._gl = []  # this energy's OpenGL objects, released with it: a fit makes many energies
        if surface not in SURFACES:
            raise ValueError(f"unknown surface {surface!r}; expected one of {SURFACES}")
        self.mgl = moderngl
        self.model = model
        self.setup = setup
        self.surface = surface
        self.evaluations = 0
        self.ctx = ctx = gl_context()
        self.renderer_name = gl_renderer_name()
        self.K = K = len(setup.studio)
        self.h, self.w = h, w = setup.input_windows.shape[1:]
        self.counted = window_pixels(setup)  # tiles are h x w; a smaller window fills its top-left
        self.moving = tuple(setup.moving) if setup.prerender else tuple(range(SEGMENTS))
        static = tuple(s for s in range(SEGMENTS) if s not in self.moving)
        budget = ATLAS_PIXELS_SOFTWARE if is_software_renderer() else ATLAS_PIXELS_GPU
        side = int(ctx.info["GL_MAX_RENDERBUFFER_SIZE"])
        if w > side or h > side:
            raise ValueError(f"{w}x{h} windows exceed the renderer's {side}-pixel limit")
        self.max_cols = side // w
        self.chunk_poses = max(1, min(budget // (K * h * w), self.max_cols * (side // h) // K))

        local, vseg, tris, tseg = mesh_geometry(model) if surface == "mesh" else rim_geometry()
        vdata = np.empty(len(local), dtype=[("pos", "f4", 3), ("seg", "i4")])
        vdata["pos"], vdata["seg"] = local, vseg
        self.vbo = self._own(ctx.buffer(vdata.tobytes()))
        vs = VERTEX_SHADER.replace("#version 450", "#version 450\n#define RIM", 1) if surface == "ellipsoid" \
            else VERTEX_SHADER
        self.progs = {name: _shared(("program", surface, name),
                                    lambda fs=fs: ctx.program(vertex_shader=vs, fragment_shader=fs))
                      for name, fs in (("count", COUNT_SHADER), ("cover", COVER_SHADER))}
        self.parts = {}
        for part, segs in (("moving", self.moving), ("static", static)):
            tri = tris[np.isin(tseg, segs)]
            if len(tri) == 0:
                continue
            slots = np.unique(vseg[tri])  # boundary vertices move with their own segment
            seg_slot = np.zeros(SEGMENTS, dtype=np.int32)
            seg_slot[slots] = np.arange(len(slots))
            # counter-clockwise seen from outside in the world is clockwise in image coordinates
            # (v down), which are our window coordinates: flip to suit GL's default front face
            ibo = self._own(ctx.buffer(np.ascontiguousarray(tri[:, [0, 2, 1]], dtype=np.int32).tobytes()))
            vaos = {name: self._own(ctx.vertex_array(prog, [(self.vbo, "3f 1i", "in_pos", "in_seg")], index_buffer=ibo))
                    for name, prog in self.progs.items()}
            self.parts[part] = dict(slots=slots, seg_slot=tuple(int(x) for x in seg_slot), vaos=vaos)
        self.cam_buf = self._own(ctx.buffer(self._camera_table().tobytes()))
        self.xf_buf = self._own(ctx.buffer(reserve=16))
        self.count_buf = self._own(ctx.buffer(reserve=16))
        self._id = next(_INSTANCES)

        I = np.asarray(setup.input_windows, dtype=bool)
        M = self._render(np.asarray(setup.static_params, dtype=np.float64), "static")
        self.static_mask = M
        if self.counted is not None:  # beyond what is counted static and input both set: v = 0, no base (as cpu)
            I, M = I | ~self.counted, M | ~self.counted
        self.weights = setup.camera_weights
        self.base = float(np.count_nonzero(M ^ I, axis=(1, 2)) @ self.weights)
        planes = pack_planes(I).astype(np.uint32) | (pack_planes(M).astype(np.uint32) << 8)   # (P, h, w)
        self.planes = self._own(ctx.buffer(planes.tobytes()))

    # ------------------------------------------------------------------ internals

    def _own(self, obj):
        self._gl.append(obj)
        return obj

    def _camera_table(self) -> np.ndarray:
        """(K * CAMERA_VEC4S, 4) float32, the layout the vertex shader reads."""
        rows = []
        for cam, win in zip(self.setup.studio, self.setup.windows):
            Kc, d = cam.K, cam.dist
            rows += [*np.hstack([cam.R, cam.t[:, None]]),
                     (Kc[0, 0], Kc[0, 1], Kc[0, 2], Kc[1, 1]),
                     (Kc[1, 2], win.x0, win.y0, 1.0 if cam.has_distortion else 0.0),
                     (d[0], d[1], d[2], d[3]), (d[4], *cam.center)]
        return np.asarray(rows, dtype=np.float32)

    def _atlas(self, tiles: int, cover: bool) -> tuple:
        """(framebuffer, tile columns, size) of an atlas of at least ``tiles`` h x w tiles.

        Tile counts are rounded up to powers of two so that few atlases are ever made.
        """
        tiles = min(1 << (tiles - 1).bit_length(), self.chunk_poses * self.K)
        cols = max(1, min(tiles, self.max_cols, int(np.ceil(np.sqrt(tiles * self.h / self.w)))))
        size = (cols * self.w, -(-tiles // cols) * self.h)

        def make():
            color = [self.ctx.renderbuffer(size, components=1, dtype="f1")] if cover else []
            return self.ctx.framebuffer(color_attachments=color, depth_attachment=self.ctx.depth_renderbuffer(size))

        return _shared(("atlas", size, cover), make), cols, size

    def _upload(self, params: np.ndarray, part: str) -> None:
        """(B, 35) -> the storage buffer of (B, S, 3, 4) world maps of ``part``'s slots."""
        pose = forward_kinematics(self.model, params)
        slots = self.parts[part]["slots"]
        xf = np.empty((len(params), len(slots), 3, 4), dtype=np.float32)
        if self.surface == "mesh":
            xf[..., :3], xf[..., 3] = pose.rotations[:, slots], pose.origins[:, slots]
        else:
            centres, A = ellipsoid_world(self.model, pose.rotations, pose.origins, slots)
            xf[..., :3], xf[..., 3] = A, centres
        if self.xf_buf.size < xf.nbytes:
            self.xf_buf.orphan(xf.nbytes)
        self.xf_buf.write(xf)

    def _draw(self, B: int, part: str, program: str) -> None:
        """Issue the draws of B uploaded poses, chunked to the atlas; reads nothing back."""
        prog, info = self.progs[program], self.parts[part]
        chunk = min(B, self.chunk_poses)
        fbo, cols, size = self._atlas(chunk * self.K, cover=program == "cover")
        if prog.extra != (self._id, part, size):  # shared programs: set uniforms only on change
            prog.extra = (self._id, part, size)
            for name, value in (("n_cams", self.K), ("n_slots", len(info["slots"])), ("seg_slot", info["seg_slot"]),
                                ("tile_cols", cols), ("tile_size", (float(self.w), float(self.h))),
                                ("atlas_size", (float(size[0]), float(size[1]))), ("tile_px", (self.w, self.h))):
                if name in prog:
                    prog[name].value = value
        self.xf_buf.bind_to_storage_buffer(0)
        self.cam_buf.bind_to_storage_buffer(1)
        fbo.use()
        self.ctx.enable(self.mgl.DEPTH_TEST | self.mgl.CULL_FACE)
        for flag in GL_CLIP_DISTANCES:
            self.ctx.enable_direct(flag)
        try:
            for first in range(0, B, chunk):
                fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
                prog["inst_base"].value = first * self.K
                info["vaos"][program].render(self.mgl.TRIANGLES, instances=min(chunk, B - first) * self.K)
        finally:
            for flag in GL_CLIP_DISTANCES:
                self.ctx.disable_direct(flag)
            self.ctx.disable(self.mgl.DEPTH_TEST | self.mgl.CULL_FACE)

    def _render(self, params: np.ndarray, part: str) -> np.ndarray:
        """(35,) -> (K, h, w) bool coverage of ``part`` ("moving" or "static")."""
        K, h, w = self.K, self.h, self.w
        if part not in self.parts:
            return np.zeros((K, h, w), dtype=bool)
        self._upload(params[None], part)
        self._draw(1, part, "cover")
        fbo, cols, size = self._atlas(K, cover=True)
        img = np.frombuffer(fbo.read(components=1, dtype="f1", alignment=1), np.uint8).reshape(size[1], size[0])
        tiles = np.stack([img[r * h:(r + 1) * h, c * w:(c + 1) * w] for r, c in (divmod(k, cols) for k in range(K))])
        return tiles > 0 if self.counted is None else (tiles > 0) & self.counted

    # ---------------------------------------------------------------------- interface

    def __call__(self, params: np.ndarray) -> np.ndarray:
        """(B, 35) or (35,) -> (B,) float64 energies (pixels, weighted as the cpu energy's)."""
        p = np.atleast_2d(np.asarray(params, dtype=np.float64))
        B = len(p)
        self.evaluations += B
        if "moving" not in self.parts:
            return np.full(B, self.base)
        self._upload(p, "moving")
        nbytes = B * self.K * 4
        if self.count_buf.size < nbytes:
            self.count_buf.orphan(nbytes)
        self.count_buf.clear()
        self.count_buf.bind_to_storage_buffer(2)
        self.planes.bind_to_storage_buffer(3)
        self._draw(B, "moving", "count")
        self.ctx.memory_barrier(self.mgl.BUFFER_UPDATE_BARRIER_BIT)
        counts = np.frombuffer(self.count_buf.read(nbytes), dtype=np.int32).reshape(B, self.K)
        return self.base + counts @ self.weights

    def render(self, params: np.ndarray) -> np.ndarray:
        """(35,) -> (K, h, w) bool: the model's silhouette windows (moving and static parts)."""
        return self._render(np.asarray(params, dtype=np.float64).reshape(-1)[:PARAM_COUNT], "moving") | self.static_mask

    def release(self) -> None:
        """Free this energy's OpenGL objects now (garbage collection does it otherwise)."""
        while self._gl:
            self._gl.pop().release()

    def __del__(self):
        try:
            self.release()
        except Exception:  # at interpreter exit the context may already be gone
            pass
