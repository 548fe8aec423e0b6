"""Scene normalisation into the unit sphere, from the cameras (and the masks when there are some).

NeuS models the object inside the unit sphere. ``Normalization`` maps world points ``x`` to
``u = (x - center) / radius`` and back; it is stored as ``normalization.json`` beside the SDF so
that the mesh and every hit are returned in world coordinates.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import torch
from jaxtyping import Bool, Float
from torch import Tensor

from ..data.scene import Cameras
from ..errors import InputError
from ..io.atomic import write_text_atomic


@dataclass(frozen=True)
class Normalization:
    center: tuple[float, float, float]
    """world point mapped to the origin"""
    radius: float
    """world length mapped to 1"""

    def to_unit(self, x: Float[Tensor, "*bs 3"]) -> Float[Tensor, "*bs 3"]:
        return (x - x.new_tensor(self.center)) / self.radius

    def to_world(self, u: Float[Tensor, "*bs 3"]) -> Float[Tensor, "*bs 3"]:
        return u * self.radius + u.new_tensor(self.center)

    def save(self, path: Path) -> None:
        write_text_atomic(path, json.dumps({"center": list(self.center), "radius": self.radius,
                                            "to_unit": "u = (x - center) / radius"}, indent=2) + "\n")

    @staticmethod
    def load(path: Path) -> "Normalization":
        try:
            d = json.loads(Path(path).read_text())
            center = tuple(float(c) for c in d["center"])
            radius = float(d["radius"])
        except (OSError, ValueError, KeyError, TypeError) as e:
            raise InputError(path, f"not a normalization file ({e})") from None
        if len(center) != 3 or not radius > 0:
            raise InputError(path, "normalization needs a 3-vector center and a positive radius")
        return Normalization(center, radius)  # type: ignore[arg-type]


def look_at_center(c2w: Float[Tensor, "N 4 4"]) -> Float[Tensor, "3"]:
    """The point closest (least squares) to every camera's optical axis: where the cameras look."""
    o, d = c2w[:, :3, 3].double(), c2w[:, :3, 2].double()
    P = torch.eye(3, dtype=torch.float64) - d.unsqueeze(-1) * d.unsqueeze(-2)        # (N, 3, 3)
    A, b = P.sum(0), (P @ o.unsqueeze(-1)).sum(0).squeeze(-1)
    if torch.linalg.matrix_rank(A) < 3:          # all axes parallel: fall back to the cameras' centroid
        return o.mean(0)
    return torch.linalg.solve(A, b)


def visual_hull(cameras: Cameras, masks: Bool[Tensor, "N H W"], center: Tensor, half: float,
                res: int = 96) -> Float[Tensor, "M 3"]:
    """Centres of the voxels of a ``res^3`` grid (cube of half-size ``half`` about ``center``) that at least
    half of the views see, each of them inside its mask (views that do not see a voxel do not carve it)."""
    g = (torch.arange(res, dtype=torch.float64) + 0.5) / res * 2 - 1
    pts = torch.stack(torch.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3) * half + center
    keep = torch.ones(len(pts), dtype=torch.bool)
    seen = torch.zeros(len(pts), dtype=torch.long)
    for v in range(len(cameras)):
        w2c = torch.linalg.inv(cameras.c2w[v].double())
        pc = pts @ w2c[:3, :3].T + w2c[:3, 3]
        uvw = pc @ cameras.K[v].double().T
        z = uvw[:, 2]
        front = z > 1e-9
        col = torch.floor(uvw[:, 0] / z.clamp_min(1e-9)).long()
        row = torch.floor(uvw[:, 1] / z.clamp_min(1e-9)).long()
        inside = front & (col >= 0) & (col < cameras.width) & (row >= 0) & (row < cameras.height)
        m = torch.zeros(len(pts), dtype=torch.bool)
        m[inside] = masks[v][row[inside], col[inside]]
        keep &= m | ~inside
        seen += inside.long()
    return pts[keep & (2 * seen >= len(cameras))]


def normalization_from_cameras(cameras: Cameras, masks: Bool[Tensor, "N H W"] | None = None,
                               margin: float = 1.15, root: Path | None = None) -> Normalization:
    """Centre and radius of a sphere that holds the object.

    With masks: the bounding sphere of the visual hull (voxel carving), times ``margin``. Without:
    the centre the optical axes meet at, and the sphere about it whose outline holds the whole frame
    of the camera that sees it largest, corners included (the object may fill a view to its corners,
    and is assumed not to overflow it). The sphere that camera sees whole, 1.3-1.4 times smaller on
    usual lenses, cut off objects that reach into the corners: the background model took them.
    """
    c2w = cameras.c2w.double()
    center = look_at_center(c2w)
    dist = (c2w[:, :3, 3] - center).norm(dim=-1)
    if masks is not None:
        half = float(dist.max())
        pts = visual_hull(cameras, masks, center, half)
        if len(pts) == 0:
            raise InputError(root, "the masks carve away everything: do masks and cameras agree?")
        voxel = 2 * half / 96 * math.sqrt(3)
        lo, hi = pts.min(0).values, pts.max(0).values
        c = 0.5 * (lo + hi)
        r = float((pts - c).norm(dim=-1).max()) + voxel
        return Normalization(tuple(float(x) for x in c), r * margin)  # type: ignore[arg-type]
    r = float((dist * torch.sin(corner_angle(cameras))).min())
    return Normalization(tuple(float(x) for x in center), r)  # type: ignore[arg-type]


def corner_angle(cameras: Cameras) -> Float[Tensor, "N"]:
    """Each view's largest angle between its optical axis and the ray through a corner of its frame."""
    w, h = cameras.width, cameras.height
    corners = torch.tensor([[0.0, 0.0, 1.0], [w, 0.0, 1.0], [0.0, h, 1.0], [w, h, 1.0]], dtype=torch.float64)
    rays = corners @ torch.linalg.inv(cameras.K.double()).transpose(-1, -2)              # (N, 4, 3), z = 1
    return torch.atan(rays[..., :2].norm(dim=-1)).amax(-1)
