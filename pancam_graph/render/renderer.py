"""Headless OpenGL (moderngl on EGL; Mesa's llvmpipe renders on the CPU) images of the terrain
through a pinhole camera with the rig's exact intrinsics.

The ground's albedo is procedural noise of the world position at several scales (5 cm to 8 m),
each octave faded out where it is finer than the pixel footprint (no aliasing, so a point
looks the same from every frame); Lambertian shading from the sun, a little ambient light, a
grey sky. Sensor noise is added after reading the image back.
"""

from __future__ import annotations

import numpy as np

from ..errors import ConfigError
from ..rig import Camera
from .terrain import TILE_M, TerrainTile

_VERTEX = """
#version 330
uniform mat4 clip_T_world;
in vec4 in_vertex;
out vec3 world;
out float contrast;
void main() {
    world = in_vertex.xyz;
    contrast = in_vertex.w;
    gl_Position = clip_T_world * vec4(in_vertex.xyz, 1.0);
}
"""

_FRAGMENT = """
#version 330
uniform vec3 sun;
uniform float seed;
in vec3 world;
in float contrast;
out float albedo_out;

float hash(vec2 p) {
    p = fract(p * vec2(443.897, 441.423) + seed);
    p += dot(p, p.yx + 19.19);
    return fract((p.x + p.y) * p.x);
}

float value_noise(vec2 p) {
    vec2 i = floor(p);
    vec2 f = fract(p);
    vec2 u = f * f * (3.0 - 2.0 * f);
    return mix(mix(hash(i), hash(i + vec2(1, 0)), u.x), mix(hash(i + vec2(0, 1)), hash(i + vec2(1, 1)), u.x), u.y);
}

void main() {
    vec2 p = world.xy;
    float footprint = max(length(fwidth(p)), 1e-4);   // metres per pixel here
    float texture = 0.0;
    float total = 0.0;
    float scale = 0.05;                                 // finest octave: 5 cm
    for (int octave = 0; octave < 8; ++octave) {
        // fade an octave out as it approaches the pixel footprint (2 px per period at least)
        float keep = clamp((scale / footprint - 2.0) / 2.0, 0.0, 1.0);
        texture += keep * (value_noise(p / scale) - 0.5);
        total += keep;
        scale *= 2.0;
    }
    // pebbles: crisp blobs at two sizes, their edges smoothed over one pixel (antialiased)
    float pebbles = 0.0;
    for (int size = 0; size < 2; ++size) {
        float s = size == 0 ? 0.12 : 0.45;
        float n = value_noise(p / s + 17.0 * float(size));
        float edge = 0.5 * footprint / s;
        float keep = clamp((s / footprint - 3.0) / 3.0, 0.0, 1.0);
        pebbles += keep * (smoothstep(0.72 - edge, 0.72 + edge, n) - smoothstep(0.22 - edge, 0.22 + edge, 1.0 - n));
    }
    float albedo = 0.45 + contrast * (0.9 * texture / max(total, 1.0) * 1.6 + 0.22 * pebbles);
    vec3 normal = normalize(cross(dFdx(world), dFdy(world)));
    if (normal.z < 0.0) normal = -normal;
    float light = 0.25 + 0.75 * max(dot(normal, sun), 0.0);
    albedo_out = clamp(albedo * light, 0.0, 1.0);
}
"""


def gl_projection(camera: Camera, near: float, far: float) -> np.ndarray:
    """OpenGL clip_T_camera (camera x right, y up, z backward) reproducing the pinhole's pixels:
    OpenCV pixel centre (u, v) is window position (u + 0.5, height - v - 0.5)."""
    w, h = camera.width, camera.height
    cx, cy = camera.cx + 0.5, camera.cy + 0.5
    return np.array([
        [2 * camera.fx / w, 0.0, 1.0 - 2 * cx / w, 0.0],
        [0.0, 2 * camera.fy / h, 2 * cy / h - 1.0, 0.0],
        [0.0, 0.0, -(far + near) / (far - near), -2 * far * near / (far - near)],
        [0.0, 0.0, -1.0, 0.0],
    ])


# OpenCV camera (x right, y down, z forward) -> OpenGL camera (x right, y up, z backward)
_GL_T_CV = np.diag([1.0, -1.0, -1.0, 1.0])


class TerrainRenderer:
    """Renders grayscale images of the terrain tiles for a camera; one GL context, reused."""

    def __init__(self, tiles: list[TerrainTile], camera: Camera, seed: int = 0, near: float = 0.3,
                 far: float = 120.0, sun_elevation_deg: float = 40.0, sun_azimuth_deg: float = 135.0):
        try:
            import moderngl
        except ImportError:
            raise ConfigError("rendering needs the [render] extra: pip install 'pancam-graph[render]' "
                              "(moderngl, on EGL)") from None
        try:
            self.ctx = moderngl.create_standalone_context(backend="egl")
        except Exception as exc:  # no EGL: moderngl raises its own Error
            raise ConfigError(f"no headless OpenGL (EGL) context: {exc}") from None
        self.camera, self.far = camera, far
        self.projection = gl_projection(camera, near, far)
        self.program = self.ctx.program(vertex_shader=_VERTEX, fragment_shader=_FRAGMENT)
        el, az = np.deg2rad(sun_elevation_deg), np.deg2rad(sun_azimuth_deg)
        self.program["sun"].value = (float(np.cos(el) * np.cos(az)), float(np.cos(el) * np.sin(az)), float(np.sin(el)))
        self.program["seed"].value = float(seed % 997) * 0.013
        self.tiles = []
        for tile in tiles:
            vbo = self.ctx.buffer(tile.vertices.tobytes())
            ibo = self.ctx.buffer(tile.triangles.tobytes())
            vao = self.ctx.vertex_array(self.program, [(vbo, "4f", "in_vertex")], index_buffer=ibo)
            self.tiles.append((tile.centre, vao))
        self.fbo = self.ctx.framebuffer(
            color_attachments=[self.ctx.renderbuffer((camera.width, camera.height), components=1, dtype="f4")],
            depth_attachment=self.ctx.depth_renderbuffer((camera.width, camera.height)))

    def render(self, world_T_camera: np.ndarray) -> np.ndarray:
        """Albedo x shading in [0, 1] (height, width) float32 seen by the camera at world_T_camera
        (OpenCV camera frame); 0.6 where the sky is."""
        import moderngl

        camera_T_world = np.linalg.inv(world_T_camera)
        clip = self.projection @ _GL_T_CV @ camera_T_world
        self.program["clip_T_world"].write(clip.T.astype("f4").tobytes())  # GLSL is column-major
        self.fbo.use()
        self.ctx.clear(0.6, 0.6, 0.6, 1.0, depth=1.0)
        self.ctx.enable(moderngl.DEPTH_TEST)
        here = world_T_camera[:2, 3]
        reach = self.far + TILE_M
        for centre, vao in self.tiles:
            if np.linalg.norm(centre - here) < reach:
                vao.render()
        raw = self.fbo.read(components=1, dtype="f4")
        image = np.frombuffer(raw, dtype=np.float32).reshape(self.camera.height, self.camera.width)
        return np.flipud(image)  # OpenGL's first row is the bottom one

    def depth(self) -> np.ndarray:
        """Metric depth (camera z, m) of the last render, (height, width)."""
        raw = self.fbo.read(attachment=-1, components=1, dtype="f4")
        z = np.flipud(np.frombuffer(raw, dtype=np.float32).reshape(self.camera.height, self.camera.width))
        p = self.projection
        ndc = 2.0 * z - 1.0
        return p[2, 3] / (ndc + p[2, 2])


def sensor_image(radiance: np.ndarray, rng: np.random.Generator, noise_dn: float = 1.5) -> np.ndarray:
    """8-bit grayscale with Gaussian read noise and quantisation."""
    dn = radiance * 255.0 + rng.normal(0.0, noise_dn, radiance.shape)
    return np.clip(np.rint(dn), 0, 255).astype(np.uint8)
