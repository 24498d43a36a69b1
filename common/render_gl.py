"""OpenGL rendering (moderngl, headless EGL): the only module that touches OpenGL.

Cameras are applied in the vertex shader, lens distortion included (per vertex, which is exact
at the vertices and close between them for the mild distortion of studio lenses). Image rows
are written top row first so that arrays read back need no flipping.
"""
from __future__ import annotations

import numpy as np

from common.camera import Camera, Studio
from common.errors import UserError

NEAR_M = 0.05   # near clipping plane, metres
FAR_M = 100.0   # far clipping plane, metres
SOFTWARE_RENDERERS = ("llvmpipe", "softpipe", "swrast", "lavapipe")

_CONTEXT = None


def gl_context():
    """The process's one headless OpenGL context (EGL; never X)."""
    global _CONTEXT
    if _CONTEXT is None:
        import moderngl

        try:
            _CONTEXT = moderngl.create_standalone_context(backend="egl")
        except Exception as exc:  # moderngl raises plain Exception on EGL failures
            raise UserError(f"cannot create a headless OpenGL context via EGL ({exc}); "
                            "install libegl1 libgl1 libgl1-mesa-dri") from None
    return _CONTEXT


def gl_renderer_name() -> str:
    return gl_context().info["GL_RENDERER"]


def is_software_renderer() -> bool:
    name = gl_renderer_name().lower()
    return any(s in name for s in SOFTWARE_RENDERERS)


CAMERA_GLSL = """
uniform mat3 cam_R;
uniform vec3 cam_t;
uniform mat3 cam_K;
uniform float cam_dist[5];
uniform vec2 cam_size;

vec4 project_to_clip(vec3 world) {
    vec3 c = cam_R * world + cam_t;
    float z = c.z;
    float zs = max(z, 1e-6);
    vec2 n = c.xy / zs;
    float r2 = dot(n, n);
    float k1 = cam_dist[0], k2 = cam_dist[1], p1 = cam_dist[2], p2 = cam_dist[3], k3 = cam_dist[4];
    float radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
    vec2 d = n * radial + vec2(2.0 * p1 * n.x * n.y + p2 * (r2 + 2.0 * n.x * n.x),
                               p1 * (r2 + 2.0 * n.y * n.y) + 2.0 * p2 * n.x * n.y);
    // cam_K is column-major in GLSL: K[col][row]
    float u = cam_K[0][0] * d.x + cam_K[1][0] * d.y + cam_K[2][0];
    float v = cam_K[1][1] * d.y + cam_K[2][1];
    vec2 ndc = vec2(2.0 * (u + 0.5) / cam_size.x - 1.0, 2.0 * (v + 0.5) / cam_size.y - 1.0);
    float n_ = %(near)f, f_ = %(far)f;
    float zc = (z * (f_ + n_) - 2.0 * f_ * n_) / (f_ - n_);
    return vec4(ndc * z, zc, z);
}
""" % {"near": NEAR_M, "far": FAR_M}


def set_camera_uniforms(prog, cam: Camera) -> None:
    prog["cam_R"].write(np.asarray(cam.R, dtype="f4").T.tobytes())
    prog["cam_t"].value = tuple(float(x) for x in cam.t)
    prog["cam_K"].write(np.asarray(cam.K, dtype="f4").T.tobytes())
    prog["cam_dist"].value = tuple(float(x) for x in cam.dist)
    prog["cam_size"].value = (float(cam.width), float(cam.height))


class MeshRenderer:
    """Renders one triangle mesh (vertices change per call) into every camera of a studio.

    triangles: (T, 3) int; triangle_labels: optional (T,) int in [0, 254] for label images.
    """

    VERTEX = "#version 330\nin vec3 in_pos;\nin float in_label;\nflat out int label;\n" + CAMERA_GLSL + """
void main() { label = int(in_label + 0.5); gl_Position = project_to_clip(in_pos); }
"""
    FRAGMENT = """#version 330
flat in int label;
out float out_value;
void main() { out_value = float(label + 1) / 255.0; }
"""

    def __init__(self, studio: Studio, triangles: np.ndarray, triangle_labels: np.ndarray | None = None):
        import moderngl

        self.ctx = gl_context()
        self.studio = studio
        tri = np.asarray(triangles, dtype=np.int64)
        self.n_vertices_expected = int(tri.max()) + 1
        # one vertex per triangle corner: labels are per triangle, so corners are not shared
        self.corner_index = tri.reshape(-1)
        labels = np.zeros(len(tri)) if triangle_labels is None else np.asarray(triangle_labels, dtype=np.float64)
        self.labels = np.repeat(labels, 3).astype("f4")
        self.prog = self.ctx.program(vertex_shader=self.VERTEX, fragment_shader=self.FRAGMENT)
        self.vbo = self.ctx.buffer(reserve=len(self.corner_index) * 12)
        self.lbo = self.ctx.buffer(self.labels.tobytes())
        self.vao = self.ctx.vertex_array(self.prog, [(self.vbo, "3f", "in_pos"), (self.lbo, "1f", "in_label")])
        self.fbos = {}
        self.moderngl = moderngl

    def set_triangle_labels(self, triangle_labels: np.ndarray) -> None:
        """(T,) new per-triangle labels (e.g. shading levels) for later render_labels calls."""
        labels = np.repeat(np.asarray(triangle_labels, dtype=np.float64), 3).astype("f4")
        if labels.size != self.labels.size:
            raise ValueError(f"expected {self.labels.size // 3} labels, got {labels.size // 3}")
        self.labels = labels
        self.lbo.write(labels.tobytes())

    def _fbo(self, width: int, height: int):
        key = (width, height)
        if key not in self.fbos:
            color = self.ctx.renderbuffer((width, height), components=1, dtype="f1")
            depth = self.ctx.depth_renderbuffer((width, height))
            self.fbos[key] = self.ctx.framebuffer(color_attachments=[color], depth_attachment=depth)
        return self.fbos[key]

    def render_labels(self, vertices: np.ndarray) -> list[np.ndarray]:
        """(V, 3) world vertices -> per camera (H, W) int16 label image, -1 where empty."""
        v = np.asarray(vertices, dtype="f4")[self.corner_index]
        self.vbo.write(v.tobytes())
        out = []
        self.ctx.enable(self.moderngl.DEPTH_TEST)
        for cam in self.studio:
            fbo = self._fbo(cam.width, cam.height)
            fbo.use()
            fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
            set_camera_uniforms(self.prog, cam)
            self.vao.render(self.moderngl.TRIANGLES)
            raw = np.frombuffer(fbo.read(components=1, dtype="f1", alignment=1), dtype=np.uint8)
            out.append(raw.reshape(cam.height, cam.width).astype(np.int16) - 1)
        self.ctx.disable(self.moderngl.DEPTH_TEST)
        return out

    def render_masks(self, vertices: np.ndarray) -> list[np.ndarray]:
        """(V, 3) world vertices -> per camera (H, W) bool silhouette."""
        return [lab >= 0 for lab in self.render_labels(vertices)]
