"""Geometric checks shared by the procedural generator: near-pair search, and
oriented boxes against boxes and segments by separating axes (NumPy only).

Boxes are (centre, heading, half length, half width); every function is
vectorised over its first axis and returns booleans, "overlap" meaning the
closed shapes intersect.
"""

from __future__ import annotations

import numpy as np

_OFFSETS = np.array([(dx, dy) for dx in (-1, 0, 1) for dy in (-1, 0, 1)])


def near_pairs(a: np.ndarray, b: np.ndarray, r: float) -> tuple[np.ndarray, np.ndarray]:
    """All index pairs (i, j) with |a_i - b_j| < r, through a uniform grid of cell r."""
    a = np.asarray(a, np.float64).reshape(-1, 2)
    b = np.asarray(b, np.float64).reshape(-1, 2)
    if not len(a) or not len(b):
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    lo = np.minimum(a.min(0), b.min(0))
    ka = np.floor((a - lo) / r).astype(np.int64) + 1
    kb = np.floor((b - lo) / r).astype(np.int64) + 1
    ny = int(max(ka[:, 1].max(), kb[:, 1].max())) + 2
    keyb = kb[:, 0] * ny + kb[:, 1]
    order = np.argsort(keyb, kind="stable")
    sk = keyb[order]
    q = (ka[:, None, 0] + _OFFSETS[None, :, 0]) * ny + ka[:, None, 1] + _OFFSETS[None, :, 1]
    q = q.ravel()
    left = np.searchsorted(sk, q, "left")
    cnt = np.searchsorted(sk, q, "right") - left
    tot = int(cnt.sum())
    if not tot:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    ia = np.repeat(np.repeat(np.arange(len(a)), len(_OFFSETS)), cnt)
    within = np.arange(tot) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    jb = order[np.repeat(left, cnt) + within]
    d = a[ia] - b[jb]
    keep = (d * d).sum(1) < r * r
    return ia[keep], jb[keep]


def self_near_pairs(a: np.ndarray, r: float) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (i, j), i < j, with |a_i - a_j| < r (each unordered pair once)."""
    a = np.asarray(a, np.float64).reshape(-1, 2)
    if len(a) < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    k = np.floor((a - a.min(0)) / r).astype(np.int64) + 1
    ny = int(k[:, 1].max()) + 2
    key = k[:, 0] * ny + k[:, 1]
    order = np.argsort(key, kind="stable")
    sk = key[order]
    pts = a[order]
    # half of the 3x3 neighbourhood: the own cell (j > i in sorted order) and 4 others
    out_i, out_j = [], []
    for dx, dy in ((0, 0), (1, -1), (1, 0), (1, 1), (0, 1)):
        q = sk + dx * ny + dy
        left = np.searchsorted(sk, q, "left")
        right = np.searchsorted(sk, q, "right")
        if dx == 0 and dy == 0:
            left = np.arange(len(sk)) + 1
        cnt = np.maximum(right - left, 0)
        tot = int(cnt.sum())
        if not tot:
            continue
        ii = np.repeat(np.arange(len(sk)), cnt)
        jj = np.repeat(left - np.cumsum(cnt) + cnt, cnt) + np.arange(tot)
        d = pts[ii] - pts[jj]
        keep = (d * d).sum(1) < r * r
        out_i.append(ii[keep])
        out_j.append(jj[keep])
    if not out_i:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    i, j = order[np.concatenate(out_i)], order[np.concatenate(out_j)]
    return np.minimum(i, j), np.maximum(i, j)


def box_box_overlap(c1, h1, l1, w1, c2, h2, l2, w2) -> np.ndarray:
    """Do boxes 1 and 2 (half extents l, w) intersect? Separating axis test."""
    c1, c2 = np.asarray(c1, np.float64), np.asarray(c2, np.float64)
    return box_box_overlap_cs(c2[..., 0] - c1[..., 0], c2[..., 1] - c1[..., 1], np.cos(h1), np.sin(h1), l1, w1,
                              np.cos(h2), np.sin(h2), l2, w2)


def box_box_overlap_cs(dx, dy, cos1, sin1, l1, w1, cos2, sin2, l2, w2) -> np.ndarray:
    """box_box_overlap from the centre offset (box 2 minus box 1) and heading cosines / sines."""
    c = np.abs(cos1 * cos2 + sin1 * sin2)  # |cos| of the relative heading
    s = np.abs(cos1 * sin2 - sin1 * cos2)
    sep = np.abs(dx * cos1 + dy * sin1) > l1 + l2 * c + w2 * s
    sep |= np.abs(dy * cos1 - dx * sin1) > w1 + l2 * s + w2 * c
    sep |= np.abs(dx * cos2 + dy * sin2) > l2 + l1 * c + w1 * s
    sep |= np.abs(dy * cos2 - dx * sin2) > w2 + l1 * s + w1 * c
    return ~sep


def box_segment_overlap(c, h, hl, hw, p, q) -> np.ndarray:
    """Does box (centre c, heading h, half extents hl, hw) touch segment p-q?"""
    c, p, q = (np.asarray(x, np.float64) for x in (c, p, q))
    cos, sin = np.cos(h), np.sin(h)
    # segment end points in the box frame
    dp, dq = p - c, q - c
    px, py = dp[..., 0] * cos + dp[..., 1] * sin, -dp[..., 0] * sin + dp[..., 1] * cos
    qx, qy = dq[..., 0] * cos + dq[..., 1] * sin, -dq[..., 0] * sin + dq[..., 1] * cos
    sep = (np.minimum(px, qx) > hl) | (np.maximum(px, qx) < -hl)
    sep |= (np.minimum(py, qy) > hw) | (np.maximum(py, qy) < -hw)
    # the segment's normal axis
    ex, ey = qx - px, qy - py
    norm = np.hypot(ex, ey)
    nx, ny = -ey / np.maximum(norm, 1e-12), ex / np.maximum(norm, 1e-12)
    sep |= np.abs(px * nx + py * ny) > hl * np.abs(nx) + hw * np.abs(ny)
    return ~sep
