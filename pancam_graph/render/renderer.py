"""Headless OpenGL (moderngl on EGL; Mesa's llvmpipe renders on the CPU) images of the terrain
through a camera with exact intrinsics and, when it has one, a distorting lens.

The ground's albedo is procedural noise of the world position at several scales (6 mm to 6 m),
each octave faded out where it is finer than the pixel footprint (no aliasing, so a point
looks the same from every frame); Lambertian shading from the sun, a little ambient light, a
grey sky. Sensor noise is added after reading the image back.
"""

from __future__ import annotations

import numpy as np

from ..errors import ConfigError
from ..geometry.rig import Camera
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
#define MAX_TAPS 8
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

// Albedo averaged over a pixel's footprint: up to `taps` samples along its long side `major`
// (metres), each faded by `footprint`; an octave (or pebble size) gets two samples per period
// along the long side, so one much coarser than the pixel is looked up once, at its centre.
float ground_albedo(vec2 p, vec2 major, int taps, float footprint, bool rock) {
    float long_side = length(major);
    float texture = 0.0;
    float total = 0.0;
    float scale = 0.00625;                              // finest octave: 6 mm (what the HRC resolves)
    for (int octave = 0; octave < 11; ++octave) {
        // fade an octave out as it approaches the footprint (2 px per period at least)
        float keep = clamp((scale / footprint - 2.0) / 2.0, 0.0, 1.0);
        if (keep > 0.0) {
            float value = 0.0;
            int n = int(clamp(ceil(2.0 * long_side / scale), 1.0, float(taps)));
            for (int t = 0; t < n; ++t) {
                value += value_noise((p + major * ((float(t) + 0.5) / float(n) - 0.5)) / scale) - 0.5;
            }
            texture += keep * value / float(n);
        }
        total += keep;
        scale *= 2.0;
    }
    // pebbles: crisp blobs at two sizes, their edges smoothed over one footprint (antialiased)
    float pebbles = 0.0;
    for (int size = 0; size < 2; ++size) {
        float s = size == 0 ? 0.12 : 0.45;
        float edge = 0.5 * footprint / s;
        float keep = clamp((s / footprint - 3.0) / 3.0, 0.0, 1.0);
        if (keep > 0.0) {
            float blob = 0.0;
            int m = int(clamp(ceil(2.0 * long_side / s), 1.0, float(taps)));
            for (int t = 0; t < m; ++t) {
                float n = value_noise((p + major * ((float(t) + 0.5) / float(m) - 0.5)) / s + 17.0 * float(size));
                blob += smoothstep(0.72 - edge, 0.72 + edge, n) - smoothstep(0.22 - edge, 0.22 + edge, 1.0 - n);
            }
            pebbles += keep * blob / float(m);
        }
    }
    float c = rock ? contrast - 1.0 : contrast;
    float base = rock ? 0.38 : 0.45;
    return base + c * (0.9 * texture / max(total, 1.0) * 1.6 + (rock ? 0.0 : 0.22) * pebbles);
}

void main() {
    vec3 normal = normalize(cross(dFdx(world), dFdy(world)));
    if (normal.z < 0.0) normal = -normal;
    // rocks (contrast above 1.5) are textured on the plane their face is closest to, the ground
    // on the horizontal one: no texture stretched down a steep face
    bool rock = contrast > 1.5;
    vec3 n = abs(normal);
    vec2 p = world.xy;
    if (rock && n.x > n.z && n.x >= n.y) p = world.yz + 31.0;
    else if (rock && n.y > n.z && n.y > n.x) p = world.xz + 57.0;
    // A pixel's footprint on the ground is long along the line of sight (grazing view) and
    // short across it. Fading the texture by the long side (isotropic filtering) wipes out
    // pebbles a real camera resolves across the line of sight at 20-40 m; averaging taps along
    // the long side, each faded by the short side, integrates the pixel as a sensor does.
    vec2 dx = dFdx(p);
    vec2 dy = dFdy(p);
    float lx = length(dx);
    float ly = length(dy);
    vec2 major = lx > ly ? dx : dy;
    float minor = max(min(lx, ly), 1e-5);
    int taps = int(clamp(ceil(max(lx, ly) / minor), 1.0, float(MAX_TAPS)));
    float footprint = length(vec2(minor, max(lx, ly) / float(taps)));   // metres per tap
    float albedo = ground_albedo(p, major, taps, footprint, rock);
    float light = 0.25 + 0.75 * max(dot(normal, sun), 0.0);
    albedo_out = clamp(albedo * light, 0.0, 1.0);
}
"""

# Depth alone (the truth of measurements made on images): the same vertices, no shading.
_DEPTH_ONLY = """
#version 330
out float albedo_out;
void main() {
    albedo_out = 0.0;
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
    """Renders grayscale images of the terrain tiles for any camera; one GL context, reused."""

    def __init__(self, tiles: list[TerrainTile], seed: int = 0, near: float = 0.3, far: float = 120.0,
                 sun_elevation_deg: float = 40.0, sun_azimuth_deg: float = 135.0):
        try:
            import moderngl
        except ImportError:
            raise ConfigError("rendering needs the [render] extra: pip install 'pancam-graph[render]' "
                              "(moderngl, on EGL)") from None
        try:
            self.ctx = moderngl.create_standalone_context(backend="egl")
        except Exception as exc:  # no EGL: moderngl raises its own Error
            raise ConfigError(f"no headless OpenGL (EGL) context: {exc}") from None
        self.near, self.far = near, far
        self.program = self.ctx.program(vertex_shader=_VERTEX, fragment_shader=_FRAGMENT)
        el, az = np.deg2rad(sun_elevation_deg), np.deg2rad(sun_azimuth_deg)
        self.program["sun"].value = (float(np.cos(el) * np.cos(az)), float(np.cos(el) * np.sin(az)), float(np.sin(el)))
        self.program["seed"].value = float(seed % 997) * 0.013
        self.depth_program = self.ctx.program(vertex_shader=_VERTEX, fragment_shader=_DEPTH_ONLY)
        self.tiles, self._depth_tiles = [], []
        for tile in tiles:
            vbo = self.ctx.buffer(tile.vertices.tobytes())
            ibo = self.ctx.buffer(tile.triangles.tobytes())
            vao = self.ctx.vertex_array(self.program, [(vbo, "4f", "in_vertex")], index_buffer=ibo)
            self.tiles.append((tile.centre, vao))
            depth_vao = self.ctx.vertex_array(self.depth_program, [(vbo, "4f", "in_vertex")], index_buffer=ibo)
            self._depth_tiles.append((tile.centre, depth_vao))
        self._framebuffers: dict[tuple[int, int], object] = {}
        self._lenses: dict[Camera, _Lens] = {}
        self._last: tuple[object, Camera] | None = None

    def _framebuffer(self, size: tuple[int, int]):
        if size not in self._framebuffers:
            self._framebuffers[size] = self.ctx.framebuffer(
                color_attachments=[self.ctx.renderbuffer(size, components=1, dtype="f4")],
                depth_attachment=self.ctx.depth_renderbuffer(size))
        return self._framebuffers[size]

    def render_pinhole(self, world_T_camera: np.ndarray, camera: Camera) -> np.ndarray:
        """Albedo x shading in [0, 1] (height, width) float32 seen by an ideal pinhole camera at
        world_T_camera (OpenCV camera frame; the camera's distortion is ignored); 0.6 is sky."""
        fbo = self._draw(self.program, self.tiles, world_T_camera, camera)
        raw = fbo.read(components=1, dtype="f4")
        image = np.frombuffer(raw, dtype=np.float32).reshape(camera.height, camera.width)
        return np.flipud(image)  # OpenGL's first row is the bottom one

    def render_depth(self, world_T_camera: np.ndarray, camera: Camera) -> np.ndarray:
        """Metric depth (camera z, m) an ideal pinhole camera at world_T_camera sees, (height,
        width): render_pinhole's depth without its shading (the fragment shader is most of a
        frame's time)."""
        self._draw(self.depth_program, self._depth_tiles, world_T_camera, camera)
        return self.depth()

    def _draw(self, program, tiles: list, world_T_camera: np.ndarray, camera: Camera):
        import moderngl

        camera_T_world = np.linalg.inv(world_T_camera)
        clip = gl_projection(camera, self.near, self.far) @ _GL_T_CV @ camera_T_world
        program["clip_T_world"].write(clip.T.astype("f4").tobytes())  # GLSL is column-major
        fbo = self._framebuffer((camera.width, camera.height))
        fbo.use()
        self.ctx.clear(0.6, 0.6, 0.6, 1.0, depth=1.0)
        self.ctx.enable(moderngl.DEPTH_TEST)
        here = world_T_camera[:2, 3]
        reach = self.far + TILE_M
        for centre, vao in tiles:
            if np.linalg.norm(centre - here) < reach:
                vao.render()
        self._last = (fbo, camera)
        return fbo

    def render_top_down(self, map_T_world: np.ndarray, corner: tuple[float, float], pixel_m: float,
                        size: tuple[int, int], sun_azimuth_deg: float, sun_elevation_deg: float,
                        heights_m: tuple[float, float]) -> np.ndarray:
        """An orthographic view from above, as an orbiter's orthoimage: `size` (width, height)
        pixels of `pixel_m` whose upper-left corner is at map `corner` (x, y; rows run south),
        where map x, y = map_T_world (2x3, affine) @ (east, north, 1); lit by its own sun
        (azimuth clockwise from north). Albedo x shading in [0, 1], (height, width) float32; NaN
        where there is no rendered ground. `heights_m`: the lowest and highest ground."""
        import moderngl

        width, height = size
        x0, y0 = corner
        span_x, span_y = width * pixel_m, height * pixel_m
        low, high = heights_m
        affine = np.zeros((4, 4))
        affine[:2, [0, 1, 3]] = map_T_world
        affine[2, 2] = affine[3, 3] = 1.0
        # map x, y to clip x, y over the box; higher ground is nearer (smaller depth)
        clip_T_map = np.array([[2.0 / span_x, 0.0, 0.0, -2.0 * x0 / span_x - 1.0],
                               [0.0, 2.0 / span_y, 0.0, -2.0 * (y0 - span_y) / span_y - 1.0],
                               [0.0, 0.0, -2.0 / (high - low + 2.0), (high + low) / (high - low + 2.0)],
                               [0.0, 0.0, 0.0, 1.0]])
        self.program["clip_T_world"].write((clip_T_map @ affine).T.astype("f4").tobytes())
        sun = self.program["sun"].value
        el, az = np.deg2rad(sun_elevation_deg), np.deg2rad(sun_azimuth_deg)
        # the shader's sun is (east, north, up): azimuth from north, clockwise
        self.program["sun"].value = (float(np.cos(el) * np.sin(az)), float(np.cos(el) * np.cos(az)),
                                     float(np.sin(el)))
        fbo = self._framebuffer((width, height))
        fbo.use()
        self.ctx.clear(-1.0, -1.0, -1.0, 1.0, depth=1.0)
        self.ctx.enable(moderngl.DEPTH_TEST)
        world_T_map = np.linalg.inv(affine)
        centre = (world_T_map @ [x0 + span_x / 2, y0 - span_y / 2, 0.0, 1.0])[:2]
        reach = np.hypot(span_x, span_y) / 2 + TILE_M
        try:
            for tile_centre, vao in self.tiles:
                if np.linalg.norm(tile_centre - centre) < reach:
                    vao.render()
        finally:
            self.program["sun"].value = sun
        self._last = None
        raw = fbo.read(components=1, dtype="f4")
        image = np.flipud(np.frombuffer(raw, dtype=np.float32).reshape(height, width)).copy()
        image[image < 0.0] = np.nan
        return image

    def render(self, world_T_camera: np.ndarray, camera: Camera) -> np.ndarray:
        """What the camera sees through its lens: with distortion, a pinhole image wide enough
        for every pixel is resampled through the lens model (OpenCV's k1, k2, p1, p2)."""
        if not any(camera.distortion()):
            return self.render_pinhole(world_T_camera, camera)
        if camera not in self._lenses:
            self._lenses[camera] = _Lens(camera)
        lens = self._lenses[camera]
        return lens(self.render_pinhole(world_T_camera, lens.pinhole))

    def depth(self) -> np.ndarray:
        """Metric depth (camera z, m) of the last pinhole or depth render, (height, width)."""
        fbo, camera = self._last
        raw = fbo.read(attachment=-1, components=1, dtype="f4")
        z = np.flipud(np.frombuffer(raw, dtype=np.float32).reshape(camera.height, camera.width))
        p = gl_projection(camera, self.near, self.far)
        ndc = 2.0 * z - 1.0
        return p[2, 3] / (ndc + p[2, 2])


class _Lens:
    """A distorting lens as a resampling: every raw pixel's undistorted direction (OpenCV's
    iterative undistortion) looked up in a pinhole image that covers them all."""

    def __init__(self, camera: Camera, margin_px: int = 3):
        import cv2

        u, v = np.meshgrid(np.arange(camera.width, dtype=np.float64), np.arange(camera.height, dtype=np.float64))
        pixels = np.column_stack([u.ravel(), v.ravel()]).reshape(-1, 1, 2)
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-12)
        xy = cv2.undistortPoints(pixels, camera.matrix(), camera.distortion(), criteria=criteria).reshape(-1, 2)
        lo, hi = xy.min(axis=0), xy.max(axis=0)
        cx = -lo[0] * camera.fx + margin_px
        cy = -lo[1] * camera.fy + margin_px
        width = int(np.ceil(hi[0] * camera.fx + cx)) + margin_px + 1
        height = int(np.ceil(hi[1] * camera.fy + cy)) + margin_px + 1
        self.pinhole = Camera(fx=camera.fx, fy=camera.fy, cx=float(cx), cy=float(cy), width=width, height=height)
        map_x = (xy[:, 0] * camera.fx + cx).reshape(camera.height, camera.width).astype(np.float32)
        map_y = (xy[:, 1] * camera.fy + cy).reshape(camera.height, camera.width).astype(np.float32)
        self.maps = map_x, map_y

    def __call__(self, pinhole_image: np.ndarray) -> np.ndarray:
        import cv2

        return cv2.remap(pinhole_image, *self.maps, cv2.INTER_LINEAR)


def sensor_image(radiance: np.ndarray, rng: np.random.Generator, noise_dn: float = 1.5) -> np.ndarray:
    """8-bit grayscale with Gaussian read noise and quantisation."""
    dn = radiance * np.float32(255.0) + rng.standard_normal(radiance.shape, dtype=np.float32) * np.float32(noise_dn)
    return np.clip(np.rint(dn), 0, 255).astype(np.uint8)
