"""Cameras from Depth Anything 3's ray maps (the authors' ``use_ray_pose`` option).

The ray branch predicts, for every pixel of a ``h x w`` map, a ray ``(d, o)`` in the world frame:
``d`` the direction (unnormalised), ``o`` the camera centre, with a confidence. A pinhole camera with
rotation ``R`` (camera-to-world) and intrinsics ``K`` sends the pixel's normalised image point ``p``
(``x, y`` in ``[-1, 1]`` over the map, homogeneous) along ``d ~ R K_n^-1 p``, where ``K_n`` is the
intrinsics in those normalised units. So the map ``p -> d`` (after dividing both by their z) is a
homography ``A ~ R K_n^-1``, and:

1. ``A`` is fitted by weighted DLT inside RANSAC: 100 samples of 8 pixels drawn from the 30 % most
   confident (``n = max(8, int(0.3 N))`` candidates, one random draw per sample shared by all frames),
   each fitted by SVD of the weighted DLT system (weights ``sqrt(confidence)``); a pixel is an inlier
   when its transfer error is below 0.2; the sample with the largest summed inlier confidence wins
   and its inliers are refitted (at most 8000, drawn at random from the 95 % most confident when
   there are more). Pixels whose ray has ``|d_z| <= 1e-4`` get weight 0.
2. ``A`` (sign fixed so ``det A > 0``) is split as ``A = Q L`` (QL decomposition through QR of the
   column-reversed matrix, signs chosen so ``diag L > 0``): ``R = Q``, and ``L / L_22`` gives
   ``1 / focal`` on its diagonal and the principal point offset in its last row.
3. The centre is the confidence-weighted mean of ``o`` (same zero weights as above).

Focal lengths come back in units of half the map (``f_n``: ``fx = f_n,x W / 2`` pixels) and the principal
point in ``[0, 2]`` (``cx = p_n,x W / 2``). The random draws come from ``generator`` (``None``: torch's
global generator, as the authors' code), so a seeded generator makes the result reproducible.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .camera import invert_rigid

SAMPLES = 100
POINTS_PER_SAMPLE = 8
CANDIDATE_FRACTION = 0.3
INLIER_THRESHOLD = 0.2
MAX_REFIT_POINTS = 8000
REFIT_CONFIDENT_FRACTION = 0.95
MIN_RAY_Z = 1e-4
FRAMES_PER_BATCH = 2


def normalised_pixel_grid(height: int, width: int, device: torch.device | str) -> Tensor:
    """``(height*width, 3)`` homogeneous image points of a ``height x width`` map, row-major, in
    units where the map spans ``[-1, 1]`` (pixel centres at ``±(1 - 1/n)``): ``(x, y, 1)``."""
    shift = 1.0
    top, left = 1 - 1 / height, 1 - 1 / width
    rows = torch.linspace(-top + shift, top + shift, height, dtype=torch.float32, device=device)
    cols = torch.linspace(-left + shift, left + shift, width, dtype=torch.float32, device=device)
    grid_y, grid_x = torch.meshgrid(rows, cols, indexing="ij")
    points = torch.stack((grid_x - 1, grid_y - 1, torch.ones_like(grid_x)), dim=-1)
    return points.reshape(-1, 3)


def _divide_by_z(points: Tensor, valid: Tensor) -> Tensor:
    """``(x / z, y / z)`` where ``valid``, ``(x, y)`` elsewhere: ``(..., 3)`` -> ``(..., 2)``."""
    z = points[..., 2]
    x = torch.where(valid, points[..., 0] / z, points[..., 0])
    y = torch.where(valid, points[..., 1] / z, points[..., 1])
    return torch.stack([x, y], dim=-1)


def weighted_dlt(source: Tensor, target: Tensor, weights: Tensor) -> Tensor:
    """Homographies ``target ~ H source`` by weighted DLT (one, or a batch).

    Args:
        source, target: ``(..., K, 2)`` points; weights: ``(..., K)`` (each row of the system is scaled
            by ``sqrt(weight)``).

    Returns:
        ``(..., 3, 3)`` with ``H_22 = 1``: the right singular vector of the smallest singular value.
    """
    root = weights.sqrt().unsqueeze(-1)
    x, y = source[..., 0:1], source[..., 1:2]
    u, v = target[..., 0:1], target[..., 1:2]
    zero = torch.zeros_like(x)
    rows_u = torch.cat([-x * root, -y * root, -root, zero, zero, zero, x * u * root, y * u * root, u * root], dim=-1)
    rows_v = torch.cat([zero, zero, zero, -x * root, -y * root, -root, x * v * root, y * v * root, v * root], dim=-1)
    _, _, vh = torch.linalg.svd(torch.cat([rows_u, rows_v], dim=-2))
    homography = vh[..., -1, :].reshape(*source.shape[:-2], 3, 3)
    return homography / homography[..., 2:3, 2:3]


def _transfer_errors(homographies: Tensor, source: Tensor, target: Tensor) -> Tensor:
    """``(B, M, N)`` distances between ``H_m source_n`` and ``target_n`` for ``(B, M, 3, 3)`` homographies
    and ``(B, N, 2)`` points."""
    batch, samples = homographies.shape[:2]
    count = source.shape[1]
    homogeneous = torch.cat([source, torch.ones(batch, count, 1, dtype=source.dtype, device=source.device)], dim=2)
    repeated = homogeneous.unsqueeze(1).expand(batch, samples, count, 3).reshape(-1, count, 3)
    projected = torch.bmm(repeated, homographies.reshape(-1, 3, 3).transpose(1, 2))
    projected = (projected[:, :, :2] / projected[:, :, 2:3]).reshape(batch, samples, count, 2)
    return ((projected - target.unsqueeze(1).expand(batch, samples, count, 2)) ** 2).sum(dim=3).sqrt()


def _refit_points(confidence: Tensor, generator: torch.Generator | None) -> Tensor:
    """Indices (into the inliers) used for the refit: by decreasing confidence, or when there are more
    than :data:`MAX_REFIT_POINTS`, that many drawn at random from the most confident 95 %."""
    order = torch.argsort(confidence, descending=True)
    if len(order) > MAX_REFIT_POINTS:
        order = order[:max(int(len(order) * REFIT_CONFIDENT_FRACTION), MAX_REFIT_POINTS)]
        order = order[torch.randperm(len(order), generator=generator, device=order.device)[:MAX_REFIT_POINTS]]
    return order


def ransac_homographies(source: Tensor, target: Tensor, weights: Tensor, sample_slots: Tensor,
                        generator: torch.Generator | None) -> Tensor:
    """Weighted RANSAC homographies of a batch of frames (step 1 of the module docstring).

    Args:
        source, target: ``(B, N, 2)``; weights: ``(B, N)``.
        sample_slots: ``(samples, points)`` ranks among each frame's most confident pixels.
        generator: for the refit's random subset.

    Returns:
        ``(B, 3, 3)``.
    """
    batch, count = weights.shape
    samples, per_sample = sample_slots.shape
    candidates = torch.argsort(weights, descending=True, dim=1)[:, : _candidate_count(count)]
    picked = candidates[:, sample_slots]  # (B, samples, points)
    frame = torch.arange(batch, device=source.device).view(batch, 1, 1).expand(batch, samples, per_sample)
    fitted = weighted_dlt(source[frame, picked].flatten(0, 1), target[frame, picked].flatten(0, 1),
                          weights[frame, picked].flatten(0, 1)).unflatten(0, (batch, samples))
    inliers = _transfer_errors(fitted, source, target) < INLIER_THRESHOLD
    scores = (inliers * weights.unsqueeze(1).expand(batch, samples, count)).sum(dim=2)
    best = inliers[torch.arange(batch, device=source.device), torch.argmax(scores, dim=1)]
    refitted = []
    for index in range(batch):
        keep = best[index]
        src, dst, conf = source[index][keep], target[index][keep], weights[index][keep]
        chosen = _refit_points(conf, generator)
        if len(chosen) < 4:
            raise ValueError(f"ray map of frame {index} has {len(chosen)} RANSAC inliers; at least 4 are needed")
        refitted.append(weighted_dlt(src[chosen], dst[chosen], conf[chosen]))
    return torch.stack(refitted, dim=0)


def _candidate_count(pixels: int) -> int:
    """Pixels the samples are drawn from: the most confident 30 % (at least one sample's worth)."""
    return max(POINTS_PER_SAMPLE, int(pixels * CANDIDATE_FRACTION))


def draw_sample_slots(pixels: int, generator: torch.Generator | None, device: torch.device | str) -> Tensor:
    """``(SAMPLES, POINTS_PER_SAMPLE)`` distinct ranks per sample among the candidates (step 1)."""
    count = _candidate_count(pixels)
    return torch.stack([torch.randperm(count, generator=generator, device=device)[:POINTS_PER_SAMPLE]
                        for _ in range(SAMPLES)], dim=0)


def ql_decomposition(matrix: Tensor) -> tuple[Tensor, Tensor]:
    """``matrix = Q L`` with ``Q`` orthogonal and ``L`` lower triangular with a positive diagonal
    (QR of the column-reversed matrix, reversed back)."""
    reverse = torch.tensor([[0, 0, 1], [0, 1, 0], [1, 0, 0]], device=matrix.device).float()
    q_reversed, r_reversed = torch.linalg.qr(torch.matmul(matrix, reverse))
    q = torch.matmul(q_reversed, reverse)
    lower = torch.matmul(torch.matmul(reverse, r_reversed), reverse)
    signs = torch.sign(torch.diag(lower))
    for axis in range(3):
        q[:, axis] *= signs[axis]
        lower[axis] *= signs[axis]
    return q, lower


def cameras_from_rays(rays: Tensor, confidence: Tensor, generator: torch.Generator | None = None
                      ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Rotation, centre, focal length and principal point of each frame's ray map.

    Args:
        rays: ``(B, S, h, w, 6)`` ``[direction, origin]`` in the world frame.
        confidence: ``(B, S, h, w)``.
        generator: random source of the RANSAC draws.

    Returns:
        ``R_wc`` ``(B, S, 3, 3)``, centre ``(B, S, 3)``, focal ``(B, S, 2)`` and principal point
        ``(B, S, 2)`` in the normalised units of the module docstring.
    """
    batch, frames, height, width, _ = rays.shape
    flat_rays = rays.flatten(0, 1).flatten(1, 2)  # (B*S, N, 6)
    weights = confidence.flatten(0, 1).flatten(1, 2).clone()
    pixels = normalised_pixel_grid(height, width, rays.device).expand(batch * frames, -1, -1)
    slots = draw_sample_slots(pixels.shape[1], generator, rays.device)
    directions = flat_rays[:, :, :3]
    valid = (directions[:, :, 2].abs() > MIN_RAY_Z) & (pixels[:, :, 2].abs() > MIN_RAY_Z)
    source, target = _divide_by_z(pixels, valid), _divide_by_z(directions, valid)
    weights = torch.where(valid, weights, torch.zeros_like(weights))
    homographies = []
    for start in range(0, batch * frames, FRAMES_PER_BATCH):
        stop = start + FRAMES_PER_BATCH
        fitted = ransac_homographies(source[start:stop], target[start:stop], weights[start:stop], slots, generator)
        flip = torch.linalg.det(fitted) < 0
        fitted[flip] = -fitted[flip]
        homographies.append(fitted)
    homography = torch.cat(homographies, dim=0)
    rotations, focal, principal = [], [], []
    for matrix in homography:
        q, lower = ql_decomposition(matrix)
        lower = lower / lower[2][2]
        rotations.append(q)
        focal.append(torch.stack((lower[0][0], lower[1][1])))
        principal.append(torch.stack((lower[2][0], lower[2][1])))
    centre = torch.sum(flat_rays[:, :, 3:] * weights.unsqueeze(-1), dim=1) / torch.sum(weights, dim=-1, keepdim=True)
    return (torch.stack(rotations).reshape(batch, frames, 3, 3), centre.reshape(batch, frames, 3),
            1.0 / torch.stack(focal).reshape(batch, frames, 2), torch.stack(principal).reshape(batch, frames, 2) + 1.0)


def extrinsics_intrinsics_from_rays(rays: Tensor, confidence: Tensor, image_hw: tuple[int, int],
                                    generator: torch.Generator | None = None) -> tuple[Tensor, Tensor]:
    """w2c extrinsics ``(B, S, 3, 4)`` and intrinsics ``(B, S, 3, 3)`` on the ``image_hw`` grid from ray maps."""
    rotation, centre, focal, principal = cameras_from_rays(rays, confidence, generator)
    batch, frames = rotation.shape[:2]
    bottom = torch.tensor([0, 0, 0, 1], dtype=rotation.dtype, device=rotation.device).expand(batch, frames, 1, 4)
    c2w = torch.cat([torch.cat([rotation, centre.unsqueeze(-1)], dim=-1), bottom], dim=-2)
    extrinsics = invert_rigid(c2w)[:, :, :3, :]
    height, width = image_hw
    intrinsics = torch.eye(3, 3)[None, None].repeat(batch, frames, 1, 1).to(rotation.device)
    intrinsics[:, :, 0, 0] = focal[:, :, 0] / 2 * width
    intrinsics[:, :, 1, 1] = focal[:, :, 1] / 2 * height
    intrinsics[:, :, 0, 2] = principal[:, :, 0] * width * 0.5
    intrinsics[:, :, 1, 2] = principal[:, :, 1] * height * 0.5
    return extrinsics, intrinsics
