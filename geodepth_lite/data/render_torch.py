"""The tube rendered in torch on any device: the same frames as ``render.Renderer`` without VTK.

A z-buffer rasteriser of ``tube.py``'s triangle mesh with the VTK renderer's camera, lights
and material (its OpenGL fragment shader, term for term), so that a dataset can be made where
the GPU is (no VTK, no display). Per frame:

- camera: ``core/camera.py``'s convention (OpenCV frame, K in pixels, pixel centres at integer
  coordinates); a pixel is covered when the ray through its centre meets a triangle, and its
  depth is the z-depth of that meeting point in [near, far] (0 elsewhere), so depth is the
  mesh's, as the VTK z-buffer's (triangles cut by the near plane are handled exactly: the
  coverage test works on rays, not on projected vertices);
- shading (``render.Renderer``, VTK's positional lights): at the meeting point, with the
  perspective-correct interpolated normal, texture coordinate and the view direction,
  ``ambient tint + sum_lights att (diffuse tint max(n.l, 0) + specular spec_color r.v^power) c_l``,
  att = 1 / d^2 (attenuation (0, 0, 1)), c_l the light's colour x intensity, times the texture
  colour (bilinear, repeating: OpenGL's GL_LINEAR without mipmaps), clamped and rounded to 8 bits;
- ``cast_rays``: ``tube.TubeMesh.cast_rays`` (the auto-exposure rays) on the same triangles.

Rasterisation is vectorised: triangles outside the view are culled, each remaining triangle's
pixel bounding box (of its part in front of the near plane) lists candidate pixels, the ray
test keeps the covered ones, and one ``scatter_reduce`` over (z bits, triangle) keys picks the
nearest, the lowest triangle index on a tie: deterministic on every device. ``render_batch``
renders many poses of one tube at once.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from geodepth_lite.core import camera as cam
from geodepth_lite.data.render import DEFAULT_MATERIAL, DEFAULT_MUCOSA_COLOR, Light

NEAR, FAR = cam.DEPTH_RANGE
MAX_CANDIDATES = 1 << 25  # candidate (pixel, triangle) pairs per rasterised chunk: bounds the memory used


def default_device() -> torch.device:
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


class TorchRenderer:
    """Torch renderer of one tube at a time, with ``render.Renderer``'s interface.

    width, height: image size; K: 3x3 intrinsics in pixels; device: any torch device (default:
    CUDA when available). ``render(T_world_cam, lights)`` returns numpy (rgb H x W x 3 uint8,
    depth H x W float32, 0 = no surface in [near, far]); ``render_batch`` many at once as tensors.
    """

    def __init__(self, width: int, height: int, K=None, near: float = NEAR, far: float = FAR,
                 device: str | torch.device | None = None):
        self.width, self.height = int(width), int(height)
        self.K = np.asarray(cam.intrinsics(self.width, self.height) if K is None else K, dtype=np.float64)
        self.near, self.far = float(near), float(far)
        self.device = default_device() if device is None else torch.device(device)
        fx, fy, cx, cy = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]
        u = (torch.arange(self.width, dtype=torch.float64) - cx) / fx
        v = (torch.arange(self.height, dtype=torch.float64) - cy) / fy
        self._ray_x, self._ray_y = u.float().to(self.device), v.float().to(self.device)
        self.tube = None
        self.material = dict(DEFAULT_MATERIAL)
        self.color = torch.tensor(DEFAULT_MUCOSA_COLOR)
        self.specular_color = torch.ones(3)

    # scene -------------------------------------------------------------------
    def set_tube(self, tube, texture: np.ndarray | None = None, material: dict | None = None) -> None:
        """Show ``tube`` (a tube.TubeMesh) with an RGB texture (h x w x 3 uint8, periodic) and Phong material."""
        a, dev = tube.arrays, self.device
        self._points = torch.from_numpy(a["points"]).to(dev)  # float64: moved to the camera frame, then float32
        self._tris = torch.from_numpy(a["triangles"]).to(dev)
        corners = self._points[self._tris]
        self._centres = corners.mean(1)  # bounding spheres of the triangles (``cast_rays``)
        self._radii = (corners - self._centres[:, None]).norm(dim=-1).amax(1)
        self._normals = torch.from_numpy(a["normals"]).to(dev)
        self._tcoords = torch.from_numpy(a["tcoords"]).to(dev)
        # as VTK shows a numpy image (pyvista.Texture): its last row is texture row 0 (t = 0)
        self._texture = (None if texture is None else
                         torch.from_numpy(np.ascontiguousarray(texture[::-1, :, :3])).to(dev).float() / 255.0)
        self.material = dict(DEFAULT_MATERIAL, **(material or {}))
        self.color = torch.ones(3) if texture is not None else torch.tensor(DEFAULT_MUCOSA_COLOR)
        self.specular_color = torch.ones(3)
        self.tube = tube

    def set_material(self, material: dict) -> None:
        """Phong coefficients {ambient, diffuse, specular, specular_power} of the mucosa (per frame)."""
        self.material = {k: float(material[k]) for k in DEFAULT_MATERIAL}

    def set_tint(self, tint) -> None:
        """Per-sample mucosa colour (multiplies the texture); as VTK's ``SetColor``, it is the ambient,
        diffuse and specular colour alike."""
        c = torch.tensor([float(min(max(t, 0.0), 1.0)) for t in tint], dtype=torch.float32)
        self.color, self.specular_color = c, c.clone()

    # frames ------------------------------------------------------------------
    def render(self, T_world_cam, lights: list | None = None) -> tuple[np.ndarray, np.ndarray]:
        """One frame: (rgb H x W x 3 uint8, depth H x W float32 z-depth; 0 = no surface in [near, far])."""
        rgb, depth = self.render_batch([T_world_cam], [lights])
        return rgb[0].cpu().numpy(), depth[0].cpu().numpy()

    def render_batch(self, poses, lights: list, tints=None, materials=None) -> tuple[torch.Tensor, torch.Tensor]:
        """Frames of the shown tube from ``poses`` (T_world_cam each), ``lights[i]`` a list of render.Light
        (None: one white light at the lens); ``tints``/``materials`` per frame (None: the current ones).
        Returns (rgb B x H x W x 3 uint8, depth B x H x W float32) on the renderer's device."""
        n = len(poses)
        tints = [None] * n if tints is None else tints
        materials = [None] * n if materials is None else materials
        rgbs, depths = [], []
        for chunk in _chunks(self, n):
            T = torch.as_tensor(np.stack([np.asarray(poses[i], dtype=np.float64) for i in chunk]), device=self.device)
            tri, z, lam = self._rasterise(self._camera_vertices(T))
            rgb, depth = self._shade(T[:, :3, :3].float(), tri, z, lam, [lights[i] for i in chunk],
                                     [tints[i] for i in chunk], [materials[i] for i in chunk])
            rgbs.append(rgb)
            depths.append(depth)
        return torch.cat(rgbs), torch.cat(depths)

    def cast_rays(self, origin, directions) -> np.ndarray:
        """Distance from ``origin`` (3,) along each unit direction (n x 3, world frame) to the first wall hit
        (inf: none): ``tube.TubeMesh.cast_rays`` on this renderer's triangles, in float64."""
        return self.cast_rays_many(np.asarray(origin)[None], np.asarray(directions)[None])[0]

    def cast_rays_many(self, origins, directions) -> np.ndarray:
        """``cast_rays`` for F origins (F x 3) with n directions each (F x n x 3): distances F x n.

        Only the (triangle, ray) pairs whose bounding sphere the ray passes through, among the triangles
        reaching into the cone of that origin's rays (``_in_cone``), get the exact test. One batch on a GPU;
        on the CPU one origin at a time (fewer large gathers; the same numbers: every step is per pair)."""
        o = torch.as_tensor(np.asarray(origins, dtype=np.float64), device=self.device)
        d = torch.as_tensor(np.asarray(directions, dtype=np.float64), device=self.device)
        if self.device.type == "cpu":
            return np.concatenate([self._cast(o[i:i + 1], d[i:i + 1]) for i in range(len(o))])
        return self._cast(o, d)

    def _cast(self, o: torch.Tensor, d: torch.Tensor) -> np.ndarray:
        F, n = d.shape[:2]
        frame, keep = torch.nonzero(_in_cone(self._centres[None] - o[:, None], self._radii, d), as_tuple=True)
        c, r = self._centres[keep] - o[frame], self._radii[keep]  # per (frame, triangle) pair
        dx, dy, dz = (d[..., i].contiguous() for i in range(3))  # F x n each
        along = c[:, 0:1] * dx[frame] + c[:, 1:2] * dy[frame] + c[:, 2:3] * dz[frame]  # pairs x n
        near = ((c * c).sum(1, keepdim=True) - along * along <= (r * r)[:, None]) & (along >= -r[:, None])
        pair, ray = torch.nonzero(near, as_tuple=True)
        f = frame[pair]
        coef = _edge_coefficients(self._points[self._tris[keep[pair]]] - o[f][:, None])
        c9, dr = coef[:, :9].view(-1, 3, 3), d[f, ray]
        e = dr[:, None, 0] * c9[:, :, 0] + dr[:, None, 1] * c9[:, :, 1] + dr[:, None, 2] * c9[:, :, 2]
        den = e.sum(1)
        inside = ((e * den[:, None]) >= 0).all(1) & (den != 0)
        t = coef[:, 9] / torch.where(den != 0, den, torch.ones_like(den))
        t = torch.where(inside & (t > 0), t, torch.full_like(t, math.inf))
        out = torch.full((F * n,), math.inf, dtype=torch.float64, device=self.device)
        return out.scatter_reduce_(0, f * n + ray, t, reduce="amin").view(F, n).cpu().numpy()

    def close(self) -> None:
        self.tube = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # internals ---------------------------------------------------------------
    def _camera_vertices(self, T: torch.Tensor) -> torch.Tensor:
        """The mesh's points in the camera frames of poses T (B x 4 x 4): R^T (p - t), B x n x 3 float32
        (explicit multiply-adds, not BLAS: the same bits at any thread count)."""
        p = self._points[None] - T[:, None, :3, 3]
        R = T[:, None, :3, :3]
        return (p[..., 0:1] * R[..., 0, :] + p[..., 1:2] * R[..., 1, :] + p[..., 2:3] * R[..., 2, :]).float()

    def _visible(self, V: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(frame, triangle) of the triangles not wholly beyond the near or far plane or one side of the view."""
        tv = V[:, self._tris]  # B x m x 3 x 3
        x, y, z = tv[..., 0], tv[..., 1], tv[..., 2]
        fx, fy, cx, cy = (float(t) for t in (self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]))
        lo_u, hi_u = (-0.5 - cx) / fx, (self.width - 0.5 - cx) / fx  # the view's edges, x/z and y/z
        lo_v, hi_v = (-0.5 - cy) / fy, (self.height - 0.5 - cy) / fy
        out = ((z < self.near).all(-1) | (z > self.far).all(-1) | (x < lo_u * z).all(-1) | (x > hi_u * z).all(-1)
               | (y < lo_v * z).all(-1) | (y > hi_v * z).all(-1))
        frame, tri = torch.nonzero(~out, as_tuple=True)
        return frame, tri

    def _bounds(self, tv: torch.Tensor) -> torch.Tensor:
        """Pixel bounding boxes (u0, u1, v0, v1), inclusive, of triangles' parts in front of the near plane."""
        near = self.near
        pts, ok = [tv], [tv[..., 2] >= near]
        for a, b in ((0, 1), (1, 2), (2, 0)):  # where an edge crosses the near plane
            pa, pb = tv[:, a], tv[:, b]
            za, zb = pa[:, 2], pb[:, 2]
            cross = (za - near) * (zb - near) < 0
            f = ((near - za) / torch.where(cross, zb - za, torch.ones_like(za))).unsqueeze(1)
            pts.append((pa + f * (pb - pa)).unsqueeze(1))
            ok.append(cross.unsqueeze(1))
        p, ok = torch.cat(pts, 1), torch.cat(ok, 1)
        zz = torch.where(ok, p[..., 2], torch.ones_like(p[..., 2]))
        u = self.K[0, 0] * p[..., 0] / zz + self.K[0, 2]
        v = self.K[1, 1] * p[..., 1] / zz + self.K[1, 2]
        big = torch.full_like(u, math.inf)
        u0, u1 = torch.where(ok, u, big).amin(1), torch.where(ok, u, -big).amax(1)
        v0, v1 = torch.where(ok, v, big).amin(1), torch.where(ok, v, -big).amax(1)
        box = torch.stack([torch.ceil(u0).clamp(min=0), torch.floor(u1).clamp(max=self.width - 1),
                           torch.ceil(v0).clamp(min=0), torch.floor(v1).clamp(max=self.height - 1)], 1)
        return box.long()

    def _rasterise(self, V: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """For camera-frame vertices V (B x n x 3): the nearest triangle per pixel (B x H x W long, -1: none),
        its z-depth (B x H x W) and barycentric weights (B x H x W x 3)."""
        frame, tri = self._visible(V)
        tv = V[frame[:, None], self._tris[tri]]  # k x 3 x 3
        coef, box = _edge_coefficients(tv), self._bounds(tv)
        bw, bh = (box[:, 1] - box[:, 0] + 1).clamp(min=0), (box[:, 3] - box[:, 2] + 1).clamp(min=0)
        count = bw * bh
        owner = torch.repeat_interleave(torch.arange(len(count), device=self.device), count)
        local = torch.arange(len(owner), device=self.device) - torch.repeat_interleave(torch.cumsum(count, 0) - count,
                                                                                        count)
        w_o = bw.index_select(0, owner)
        pu = box[:, 0].index_select(0, owner) + local % w_o
        pv = box[:, 2].index_select(0, owner) + torch.div(local, w_o, rounding_mode="floor")
        e = _edge_values(coef.index_select(0, owner), self._ray_x.index_select(0, pu), self._ray_y.index_select(0, pv))
        den = e.sum(1)
        z = coef[:, 9].index_select(0, owner) / torch.where(den != 0, den, torch.ones_like(den))
        ok = ((e * den[:, None]) >= 0).all(1) & (den != 0) & (z >= self.near) & (z <= self.far)
        pix = (frame.index_select(0, owner) * self.height + pv) * self.width + pu
        return self._depth_test(len(V), pix[ok], owner[ok], z[ok], coef, tri)

    def _depth_test(self, n_frames, pix, owner, z, coef, tri) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The nearest candidate per pixel (the lowest ``owner`` on a tie): (mesh triangle, z, weights) per frame."""
        H, W, dev = self.height, self.width, self.device
        none = torch.iinfo(torch.int64).max
        key = (z.view(torch.int32).long() << 32) | owner  # positive floats: their bits sort as the numbers do
        best = torch.full((n_frames * H * W,), none, dtype=torch.int64, device=dev)
        best.scatter_reduce_(0, pix, key, reduce="amin")
        hit = best != none
        win = torch.where(hit, best & 0xFFFFFFFF, torch.zeros_like(best))
        tri_px = torch.where(hit, tri.index_select(0, win) if len(tri) else win, torch.full_like(best, -1))
        z_px = torch.where(hit, (best >> 32).int().view(torch.float32), torch.zeros((), device=dev))
        # barycentric weights of the winners (perspective-correct: of the 3D meeting point)
        rx = self._ray_x.repeat(n_frames * H)
        ry = self._ray_y.repeat_interleave(W).repeat(n_frames)
        e = _edge_values(coef.index_select(0, win) if len(coef) else torch.zeros(len(win), 10, device=dev), rx, ry)
        den = e.sum(1, keepdim=True)
        lam = e / torch.where(den != 0, den, torch.ones_like(den))
        return tri_px.view(n_frames, H, W), z_px.view(n_frames, H, W), lam.view(n_frames, H, W, 3)

    def _frame_constants(self, lights: list, tints: list, materials: list) -> dict:
        """Per frame of a batch: mucosa and specular colours (B x 3), Phong coefficients (B each), and the lights'
        positions and colour x intensity (B x L x 3; a frame with fewer lights gets black ones: adding their
        zero terms changes no bit)."""
        n, dev = len(lights), self.device
        lights = [[Light((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), 1.0)] if ls is None else ls for ls in lights]
        n_l = max(len(ls) for ls in lights)
        pos, col = np.zeros((n, n_l, 3), np.float32), np.zeros((n, n_l, 3), np.float32)
        for i, ls in enumerate(lights):
            for k, light in enumerate(ls):
                pos[i, k] = light.offset
                col[i, k] = np.float32(light.color) * np.float32(light.intensity)
        colour = torch.stack([self.color if t is None else torch.tensor([min(max(float(c), 0.0), 1.0) for c in t])
                              for t in tints]).float()
        spec = torch.stack([self.specular_color if t is None else colour[i] for i, t in enumerate(tints)]).float()
        mats = [self.material if mt is None else mt for mt in materials]
        coef = {k: torch.tensor([float(mt[k]) for mt in mats], dtype=torch.float32, device=dev)[:, None, None, None]
                for k in DEFAULT_MATERIAL}
        return dict(coef, colour=colour.to(dev)[:, None, None], spec=spec.to(dev)[:, None, None],
                    pos=torch.from_numpy(pos).to(dev), col=torch.from_numpy(col).to(dev))

    def _shade(self, rot, tri, z, lam, lights, tints, materials) -> tuple[torch.Tensor, torch.Tensor]:
        """VTK's fragment shader at every covered pixel of a batch: (rgb B x H x W x 3 uint8, depth B x H x W)."""
        c = self._frame_constants(lights, tints, materials)
        hit = tri >= 0
        corners = self._tris[tri.clamp(min=0)]  # B x H x W x 3
        n = (lam.unsqueeze(-1) * self._normals[corners]).sum(-2)
        R = rot[:, None, None]  # world -> camera frame (OpenCV; lighting is the same in any frame)
        n = n[..., 0:1] * R[..., 0, :] + n[..., 1:2] * R[..., 1, :] + n[..., 2:3] * R[..., 2, :]
        n = n / n.norm(dim=-1, keepdim=True).clamp(min=1e-12)
        p = torch.stack([self._ray_x[None, None, :] * z, self._ray_y[None, :, None] * z, z], -1)
        view = -p / p.norm(dim=-1, keepdim=True).clamp(min=1e-12)
        diffuse, specular = torch.zeros_like(p), torch.zeros_like(p)
        for k in range(c["pos"].shape[1]):
            ld = p - c["pos"][:, None, None, k]
            dist = ld.norm(dim=-1, keepdim=True)
            ld = ld / dist.clamp(min=1e-12)
            att = 1.0 / (dist * dist)
            df = torch.clamp(att * (n * -ld).sum(-1, keepdim=True), min=0.0)
            refl = ld - 2.0 * (n * ld).sum(-1, keepdim=True) * n
            sf = torch.sign(df) * att * torch.clamp((refl * view).sum(-1, keepdim=True), min=1e-5).pow(
                c["specular_power"])
            diffuse = diffuse + df * c["col"][:, None, None, k]
            specular = specular + sf * c["col"][:, None, None, k]
        out = (c["ambient"] * c["colour"] + diffuse * (c["diffuse"] * c["colour"])
               + specular * (c["specular"] * c["spec"]))
        if self._texture is not None:
            out = out * _sample_texture(self._texture, (lam.unsqueeze(-1) * self._tcoords[corners]).sum(-2))
        zero = torch.zeros((), device=self.device)
        rgb = torch.where(hit.unsqueeze(-1), torch.round(out.clamp(0.0, 1.0) * 255.0), zero)
        return rgb.to(torch.uint8), torch.where(hit, z, zero)


def _in_cone(centre: torch.Tensor, radius: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """Per origin (F) and triangle (m): whether the triangle may meet one of that origin's rays (unit directions
    ``d``, F x n x 3), i.e. its bounding sphere (``centre`` relative to the origin, F x m x 3, and ``radius``)
    reaches into the narrowest cone about the rays' mean direction that holds them all (every triangle when
    that cone is 90 degrees or wider). F x m booleans."""
    axis = d.mean(1)
    axis = axis / axis.norm(dim=1, keepdim=True).clamp(min=1e-300)
    cos_a = (d * axis[:, None]).sum(-1).amin(1)  # F
    dist = centre.norm(dim=-1)
    along = (centre * axis[:, None]).sum(-1) / dist.clamp(min=1e-300)
    angle = torch.acos(along.clamp(-1.0, 1.0))
    slack = torch.asin((radius / dist.clamp(min=1e-300)).clamp(max=1.0))
    inside = (dist <= radius) | (angle - slack <= torch.acos(cos_a.clamp(-1.0, 1.0))[:, None] + 1e-9)
    return inside | (cos_a <= 0)[:, None]


def _edge_coefficients(tv: torch.Tensor) -> torch.Tensor:
    """Per triangle (k x 3 x 3 corners, camera frame) the ray test's 10 numbers: c_i = v_j x v_k (i, j, k
    cyclic; 9) and v_0 . c_0 (1). The ray d = (x, y, 1) meets the triangle where e_i = d . c_i share the
    sign of their sum, with barycentric weights e_i / sum and z-depth (v_0 . c_0) / sum."""
    v0, v1, v2 = tv[:, 0], tv[:, 1], tv[:, 2]
    c0, c1, c2 = _cross(v1, v2), _cross(v2, v0), _cross(v0, v1)
    return torch.cat([c0, c1, c2, (v0 * c0).sum(1, keepdim=True)], 1)


def _cross(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """a x b by separate products and differences, so that b x a is exactly -(a x b) (``torch.cross`` may fuse
    a multiply-add and lose that): two triangles sharing an edge then get exactly opposite edge values, and a
    ray through the edge covers one of them (no cracks)."""
    ax, ay, az = a[:, 0], a[:, 1], a[:, 2]
    bx, by, bz = b[:, 0], b[:, 1], b[:, 2]
    return torch.stack([ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx], 1)


def _edge_values(coef: torch.Tensor, rx: torch.Tensor, ry: torch.Tensor) -> torch.Tensor:
    """e_i = (rx, ry, 1) . c_i for rows of ``_edge_coefficients`` (n x 3)."""
    c = coef[:, :9].view(-1, 3, 3)
    return rx[:, None] * c[:, :, 0] + ry[:, None] * c[:, :, 1] + c[:, :, 2]


def _sample_texture(tex: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Bilinear, repeating lookup of ``tex`` (h x w x 3, rows from t = 0) at texture coordinates ``uv`` (... x 2):
    OpenGL's GL_LINEAR with GL_REPEAT, texel centres at (i + 0.5) / size."""
    h, w = tex.shape[:2]
    x = uv[..., 0] * w - 0.5
    y = uv[..., 1] * h - 0.5
    x0, y0 = torch.floor(x), torch.floor(y)
    fx, fy = (x - x0).unsqueeze(-1), (y - y0).unsqueeze(-1)
    x0, y0 = x0.long() % w, y0.long() % h
    x1, y1 = (x0 + 1) % w, (y0 + 1) % h
    top = tex[y0, x0] * (1 - fx) + tex[y0, x1] * fx
    bottom = tex[y1, x0] * (1 - fx) + tex[y1, x1] * fx
    return top * (1 - fy) + bottom * fy


def _chunks(renderer: TorchRenderer, n: int) -> list[list[int]]:
    """Frames grouped so that each group rasterises about MAX_CANDIDATES candidate pixels at most (on the
    CPU a sixteenth of that), at a rough estimate of 4 candidates per pixel."""
    budget = MAX_CANDIDATES if renderer.device.type != "cpu" else MAX_CANDIDATES // 16
    size = max(1, budget // (4 * renderer.width * renderer.height))
    return [list(range(i, min(i + size, n))) for i in range(0, n, size)]
