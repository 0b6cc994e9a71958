"""The rendered world: a clothed body (and any others beside it), a textured floor and backdrop, per-clip lighting,
drawn by pyrender through OSMesa (software OpenGL, no display) and distorted with the rig's
lens model.

The pinhole image is rendered on a canvas large enough to hold every pixel that the
distorted image needs, then resampled (cv2.remap) through the camera's distortion: the
recorded image is what a lens with these coefficients would deliver, so the pipeline's
undistortion is exercised.
"""

from __future__ import annotations

import ctypes.util
import os
from dataclasses import dataclass
from typing import Any, Iterable, Sequence

import numpy as np

from ...cameras.projection import Camera, Rig
from ...errors import VmocapError
from .body import SEGMENT_NAMES, Body

OSMESA_HINT = "install Debian's libosmesa6 (apt-get install -y libosmesa6; scripts/setup.sh does it as root)"
ROOM_HALF = 7.0  # the backdrop walls stand behind the cameras (5 m from the centre)
ROOM_HEIGHT = 4.0


@dataclass
class Appearance:
    """Colours (RGB in [0, 1]) and lights of one clip, drawn from a seeded generator."""

    shirt: np.ndarray
    trousers: np.ndarray
    shoes: np.ndarray
    skin: np.ndarray
    hair: np.ndarray
    long_sleeves: bool
    floor: tuple[np.ndarray, np.ndarray]
    wall: np.ndarray
    sun_direction: np.ndarray  # unit vector the light travels along
    sun_intensity: float
    ambient: float

    @classmethod
    def draw(cls, rng: np.random.Generator) -> "Appearance":
        def colour(lo: float, hi: float) -> np.ndarray:
            return rng.uniform(lo, hi, 3)

        skins = np.array([[0.95, 0.80, 0.69], [0.85, 0.64, 0.50], [0.63, 0.45, 0.33], [0.40, 0.27, 0.20]])
        az, el = rng.uniform(0, 2 * np.pi), rng.uniform(np.radians(35), np.radians(75))
        d = -np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        return cls(
            shirt=colour(0.1, 0.95), trousers=colour(0.05, 0.6), shoes=colour(0.02, 0.4),
            skin=skins[rng.integers(len(skins))] * rng.uniform(0.9, 1.05), hair=colour(0.02, 0.35),
            long_sleeves=bool(rng.integers(2)), floor=(colour(0.3, 0.8), colour(0.1, 0.5)), wall=colour(0.3, 0.9),
            sun_direction=d, sun_intensity=float(rng.uniform(2.5, 4.5)), ambient=float(rng.uniform(0.3, 0.6)),
        )


def vertex_colours(body: Body, look: Appearance, rng: np.random.Generator) -> np.ndarray:
    """(V, 4) RGBA per vertex: clothing regions from each vertex's dominant segment and rest
    height, a stripe pattern on the shirt and a little per-vertex shading noise."""
    seg = np.array(SEGMENT_NAMES)[body.segment_of()]
    z = body.vertices[:, 2]
    y = body.vertices[:, 1]
    col = np.empty((len(seg), 3))
    trunk = np.isin(seg, ["pelvis", "chest"])
    col[:] = look.skin
    shirt = np.isin(seg, ["chest", "clavicle_l", "clavicle_r", "upperarm_l", "upperarm_r"]) | (trunk & (z >= 0.2))
    if look.long_sleeves:
        shirt |= np.isin(seg, ["forearm_l", "forearm_r"])
    stripes = 0.8 + 0.2 * (np.sin(z * 70.0) > 0)
    col[shirt] = look.shirt * stripes[shirt, None]
    legs = np.isin(seg, ["thigh_l", "thigh_r", "shin_l", "shin_r"]) | (trunk & (z < 0.2))
    col[legs] = look.trousers
    col[np.isin(seg, ["foot_l", "foot_r"])] = look.shoes
    hair = (seg == "head") & ((z > 0.78) | ((z > 0.66) & (y > -0.02)))
    col[hair] = look.hair
    col *= rng.uniform(0.92, 1.08, (len(col), 1))
    return np.concatenate([np.clip(col, 0, 1), np.ones((len(col), 1))], axis=1)


def vertex_normals(v: np.ndarray, faces: np.ndarray) -> np.ndarray:
    fn = np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]])
    n = np.zeros_like(v)
    for k in range(3):  # three scatter-adds, not a loop over faces
        for c in range(3):
            n[:, c] += np.bincount(faces[:, k], fn[:, c], minlength=len(v))
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)


def _texture(pyrender, img: np.ndarray):
    return pyrender.Texture(source=img, source_channels="RGB")


def _quad(pyrender, corners: np.ndarray, uv_repeat: float, img: np.ndarray, shade: float):
    """A textured rectangle (4 corners in order), drawn unlit with the given shading."""
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=np.float32) * uv_repeat
    n = np.cross(corners[1] - corners[0], corners[3] - corners[0])
    n = np.tile(n / np.linalg.norm(n), (4, 1))
    # the shader multiplies the emission by its factor twice: sqrt(shade) gives texture x shade
    f = float(np.sqrt(shade))
    mat = pyrender.MetallicRoughnessMaterial(baseColorFactor=[0.0, 0.0, 0.0, 1.0], emissiveTexture=_texture(pyrender, img),
                                             emissiveFactor=[f, f, f], metallicFactor=0.0, roughnessFactor=1.0,
                                             doubleSided=True)
    prim = pyrender.Primitive(positions=corners.astype(np.float32), normals=n.astype(np.float32),
                              texcoord_0=uv, indices=np.array([[0, 1, 2], [0, 2, 3]], dtype=np.uint32), material=mat)
    return pyrender.Mesh([prim])


def floor_image(look: Appearance, rng: np.random.Generator, size: int = 256) -> np.ndarray:
    k = np.arange(size) // (size // 8)
    check = ((k[:, None] + k[None, :]) % 2).astype(bool)
    img = np.where(check[..., None], look.floor[0], look.floor[1]) * rng.uniform(0.85, 1.15, (size, size, 1))
    return (np.clip(img, 0, 1) * 255).astype(np.uint8)


def wall_image(look: Appearance, rng: np.random.Generator, size: int = 256) -> np.ndarray:
    """Low-frequency colour blobs (cv2.resize of a coarse random grid) on the wall colour."""
    import cv2

    coarse = rng.uniform(0.75, 1.1, (8, 8, 3)).astype(np.float32)
    img = cv2.resize(coarse, (size, size), interpolation=cv2.INTER_CUBIC) * look.wall
    return (np.clip(img, 0, 1) * 255).astype(np.uint8)


def import_pyrender():
    """pyrender on OSMesa, or a clear error saying what to install."""
    os.environ["PYOPENGL_PLATFORM"] = "osmesa"
    if ctypes.util.find_library("OSMesa") is None:
        raise VmocapError(f"no OSMesa library for offscreen rendering: {OSMESA_HINT}")
    try:
        import pyrender
    except ImportError as exc:
        raise VmocapError(f"rendering needs pyrender-maintained and PyOpenGL (requirements.lock): {exc}") from None
    return pyrender


class ProgramCache:
    """pyrender's shader cache with a key that stays the same from one render to the next.

    pyrender keys its programs by OpenGL.contextdata.getContext(), which under OSMesa is a new
    pointer object on every call: each render compiled and kept one more shader program (~3 MB
    of native memory, ~13 MB per 4-camera frame set), so a long clip ran out of RAM. A renderer
    has a single context, so the shader files and defines alone identify its programs."""

    def __init__(self, inner: Any) -> None:
        self.inner = inner
        self.programs: dict[tuple, Any] = {}

    def get_program(self, vertex_shader: str, fragment_shader: str, geometry_shader: str | None = None,
                    defines: dict | None = None) -> Any:
        key = (vertex_shader, fragment_shader, geometry_shader, tuple(sorted((defines or {}).items())))
        if key not in self.programs:
            self.programs[key] = self.inner.get_program(vertex_shader, fragment_shader, geometry_shader, defines)
        return self.programs[key]

    def clear(self) -> None:
        self.programs = {}
        self.inner.clear()


def offscreen_renderer(pr: Any, width: int, height: int) -> Any:
    """An OffscreenRenderer that compiles each shader program once (ProgramCache)."""
    r = pr.OffscreenRenderer(width, height)
    r._renderer._program_cache = ProgramCache(r._renderer._program_cache)
    return r


class DistortionMap:
    """Distorted pixel grid of a camera -> pixel of a padded pinhole canvas (cv2.remap maps)."""

    def __init__(self, cam: Camera) -> None:
        u, v = np.meshgrid(np.arange(cam.width, dtype=np.float64), np.arange(cam.height, dtype=np.float64))
        xy = cam.undistort_pixels(np.stack([u, v], axis=-1)) if cam.has_distortion else \
            np.stack([(u - cam.K[0, 2]) / cam.K[0, 0], (v - cam.K[1, 2]) / cam.K[1, 1]], axis=-1)
        pu = cam.K[0, 0] * xy[..., 0] + cam.K[0, 2]
        pv = cam.K[1, 1] * xy[..., 1] + cam.K[1, 2]
        self.pad_x = int(np.ceil(max(0.0, -pu.min(), pu.max() - (cam.width - 1)))) + 2
        self.pad_y = int(np.ceil(max(0.0, -pv.min(), pv.max() - (cam.height - 1)))) + 2
        self.map_x = (pu + self.pad_x).astype(np.float32)
        self.map_y = (pv + self.pad_y).astype(np.float32)
        self.canvas = (cam.width + 2 * self.pad_x, cam.height + 2 * self.pad_y)

    def apply(self, canvas: np.ndarray) -> np.ndarray:
        import cv2

        return cv2.remap(canvas, self.map_x, self.map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


class SceneRenderer:
    """One scene (floor, walls, lights, the body's current pose) seen by every rig camera."""
    # pyrender returns linear depth (0 where nothing was drawn): the z-test compares metres

    def __init__(self, rig: Rig, body: Body, look: Appearance, seed: int, floor_z: float = 0.0,
                 centre: np.ndarray | None = None) -> None:
        centre = np.zeros(2) if centre is None else centre
        pr = import_pyrender()
        self.pr = pr
        self.rig = rig
        self.body = body
        rng = np.random.default_rng(seed)
        self.colours = vertex_colours(body, look, rng)
        # The body is drawn unlit: emission x vertex colour is the shaded colour in linear light
        # (the shader applies the 1/2.2 gamma). Factors must be floats: pyrender reads integer
        # colours as 0-255.
        self.material = pr.MetallicRoughnessMaterial(baseColorFactor=[0.0, 0.0, 0.0, 1.0], emissiveFactor=[1.0, 1.0, 1.0],
                                                     metallicFactor=0.0, roughnessFactor=1.0)
        # Lights as (direction of travel, strength): the sun and fills from three more azimuths
        # (strength `ambient` of the sun's). Everything is shaded here and drawn unlit, because
        # pyrender sums its lights in the order of a Python set: their order, and so the last
        # bit of some pixels, changed from scene to scene.
        self.lights: list[tuple[np.ndarray, float]] = [(look.sun_direction, look.sun_intensity / np.pi)]
        for k in (1, 2, 3):
            a = k * np.pi / 2
            rot = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
            self.lights.append((rot @ look.sun_direction, look.ambient * look.sun_intensity / np.pi))
        # The room is static: drawn once per camera (colour and depth); each frame draws the
        # body alone and keeps its pixels where they are nearer than the room's (a z-test).
        self.room = pr.Scene(bg_color=[0.0, 0.0, 0.0, 1.0])
        self.scene = pr.Scene(bg_color=[0.0, 0.0, 0.0, 1.0])
        cx, cy, h = float(centre[0]), float(centre[1]), ROOM_HALF
        z0, zt = floor_z, floor_z + ROOM_HEIGHT
        c = lambda x, y, z: [cx + x, cy + y, z]  # noqa: E731
        floor = np.array([c(-h, -h, z0), c(h, -h, z0), c(h, h, z0), c(-h, h, z0)])
        self.room.add(_quad(pr, floor, 7.0, floor_image(look, rng), self._shade(np.array([0.0, 0.0, 1.0]))))
        for (x0, y0), (x1, y1) in (((-h, -h), (h, -h)), ((h, -h), (h, h)), ((h, h), (-h, h)), ((-h, h), (-h, -h))):
            wall = np.array([c(x0, y0, z0), c(x1, y1, z0), c(x1, y1, zt), c(x0, y0, zt)])
            inward = -np.array([x0 + x1, y0 + y1, 0.0]) / (2 * h)
            self.room.add(_quad(pr, wall, 3.0, wall_image(look, rng), self._shade(inward)))
        ceiling = np.array([c(-h, -h, zt), c(h, -h, zt), c(h, h, zt), c(-h, h, zt)])
        self.room.add(_quad(pr, ceiling, 1.0, np.full((4, 4, 3), 200, np.uint8), 0.4))
        self.albedo = self.colours[:, :3] ** 2.2
        self.others: list[tuple[Body, np.ndarray]] = []  # more people: (body, albedo), see add_person
        self.maps = [DistortionMap(c) for c in rig]
        self.cam_nodes = []
        self.backgrounds: list[tuple[np.ndarray, np.ndarray]] = []
        self.box_size = max(m.canvas[0] for m in self.maps), max(m.canvas[1] for m in self.maps)
        self._box_renderer = None
        room_renderers: dict[tuple[int, int], Any] = {}
        for camera, m in zip(rig, self.maps):
            pose = np.eye(4)
            pose[:3, :3] = camera.R.T @ np.diag([1.0, -1.0, -1.0])  # OpenCV camera axes -> OpenGL's
            pose[:3, 3] = camera.center
            nodes = []
            for scene in (self.room, self.scene):
                # pyrender's pixel centres sit at +0.5, OpenCV's at integers: shift the principal point
                cam = pr.IntrinsicsCamera(camera.K[0, 0], camera.K[1, 1], camera.K[0, 2] + m.pad_x + 0.5,
                                          camera.K[1, 2] + m.pad_y + 0.5, znear=0.05, zfar=40.0)
                nodes.append(scene.add(cam, pose=pose))
            self.room.main_camera_node = nodes[0]
            if m.canvas not in room_renderers:
                room_renderers[m.canvas] = offscreen_renderer(pr, *m.canvas)
            rgb, depth = room_renderers[m.canvas].render(self.room)
            self.backgrounds.append((rgb, np.where(depth > 0, depth, np.inf)))
            self.cam_nodes.append(nodes[1])
        for r in room_renderers.values():
            r.delete()
        self.body_node = None

    def _shade(self, normals: np.ndarray) -> np.ndarray:
        """Lambert shading of unit normals (..., 3) under the scene's lights."""
        return 0.05 + sum(w * np.maximum(0.0, -normals @ d) for d, w in self.lights)

    def add_person(self, body: Body, look: Appearance, seed: int) -> None:
        """Another body in the scene, in its own clothes (`look`'s; its room and lights are not
        used) under the scene's lights: render() then takes its posed vertices in `others`."""
        self.others.append((body, vertex_colours(body, look, np.random.default_rng(seed))[:, :3] ** 2.2))

    def fit_box(self, frames: Iterable[np.ndarray]) -> None:
        """Draw the body in a fixed box just large enough for it in every frame and camera (one
        OSMesa context of that size: OSMesa cannot resize a context's buffer). `frames` may be a
        generator: one posed body at a time is held (with other people: all bodies' vertices
        of a frame, concatenated)."""
        boxes = [self._body_box(c, m, v, (0, 0)) for v in frames for c, m in zip(self.rig, self.maps)]
        sizes = np.array([b[2:] for b in boxes if b is not None])
        if len(sizes):
            q = 32
            w, h = (-(-sizes.max(axis=0) // q) * q).tolist()
            self.box_size = (min(w, self.box_size[0]), min(h, self.box_size[1]))
        self.close()

    def _renderer(self):
        if self._box_renderer is None:
            self._box_renderer = offscreen_renderer(self.pr, *self.box_size)
        return self._box_renderer

    @staticmethod
    def _body_box(cam: Camera, m: "DistortionMap", vertices: np.ndarray, size: tuple[int, int]) -> tuple[int, int, int, int] | None:
        """(x0, y0, w, h): a box of `size` (or the body's own size, if larger) on the canvas
        around the body's pinhole projection, inside the canvas; None when the body is not in front."""
        pc = vertices @ cam.R.T + cam.t
        pc = pc[pc[:, 2] > 0.05]
        if len(pc) == 0:
            return None
        u = cam.K[0, 0] * pc[:, 0] / pc[:, 2] + cam.K[0, 2] + m.pad_x
        v = cam.K[1, 1] * pc[:, 1] / pc[:, 2] + cam.K[1, 2] + m.pad_y
        W, H = m.canvas
        u0, u1 = max(int(np.floor(u.min())) - 2, 0), min(int(np.ceil(u.max())) + 3, W)
        v0, v1 = max(int(np.floor(v.min())) - 2, 0), min(int(np.ceil(v.max())) + 3, H)
        if u1 <= u0 or v1 <= v0:
            return None
        w, h = min(max(size[0], u1 - u0), W), min(max(size[1], v1 - v0), H)
        x0 = min(max((u0 + u1 - w) // 2, 0), W - w)
        y0 = min(max((v0 + v1 - h) // 2, 0), H - h)
        return x0, y0, w, h

    def _primitive(self, body: Body, albedo: np.ndarray, vertices: np.ndarray) -> Any:
        n = vertex_normals(vertices, body.faces)
        shade = self._shade(n)
        rgba = np.concatenate([np.clip(albedo * shade[:, None], 0, 1), np.ones((len(n), 1))], axis=1)
        return self.pr.Primitive(positions=vertices.astype(np.float32), normals=n.astype(np.float32),
                                 color_0=rgba.astype(np.float32), indices=body.faces.astype(np.uint32),
                                 material=self.material)

    def render(self, vertices: np.ndarray, others: Sequence[np.ndarray] = ()) -> list[np.ndarray]:
        """BGR uint8 images (one per rig camera) of the body with these posed vertices (and the
        people of add_person with theirs, in that order)."""
        pr = self.pr
        if len(others) != len(self.others):
            raise VmocapError(f"{len(others)} posed bodies for the {len(self.others)} other people of the scene")
        prims = [self._primitive(self.body, self.albedo, vertices)]
        prims += [self._primitive(b, a, v) for (b, a), v in zip(self.others, others)]
        if self.body_node is not None:
            self.scene.remove_node(self.body_node)
        self.body_node = self.scene.add(pr.Mesh(prims))
        everyone = np.concatenate([vertices, *others]) if len(others) else vertices
        out = []
        for c, node, m, (bg, bg_depth) in zip(self.rig, self.cam_nodes, self.maps, self.backgrounds):
            canvas = bg.copy()
            box = self._body_box(c, m, everyone, self.box_size)
            if box is not None and box[2:] != self.box_size:
                raise VmocapError(f"the body does not fit the render box {self.box_size} (call fit_box)")
            if box is not None:
                # only the body's box is drawn: the principal point moves by the box's corner
                x0, y0, w, h = box
                node.camera.cx = c.K[0, 2] + m.pad_x + 0.5 - x0
                node.camera.cy = c.K[1, 2] + m.pad_y + 0.5 - y0
                self.scene.main_camera_node = node
                rgb, depth = self._renderer().render(self.scene)
                sub = (slice(y0, y0 + h), slice(x0, x0 + w))
                body = (depth > 0) & (depth < bg_depth[sub])
                canvas[sub] = np.where(body[..., None], rgb, bg[sub])
            out.append(np.ascontiguousarray(m.apply(canvas)[..., ::-1]))
        return out

    def empty_room(self) -> list[np.ndarray]:
        """BGR images of the room without the body (as render() delivers them)."""
        return [np.ascontiguousarray(m.apply(bg)[..., ::-1]) for m, (bg, _) in zip(self.maps, self.backgrounds)]

    def close(self) -> None:
        if self._box_renderer is not None:
            self._box_renderer.delete()
            self._box_renderer = None
