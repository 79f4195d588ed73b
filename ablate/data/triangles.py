"""Scanline rasterisation of triangles with linear (barycentric) interpolation, vectorised in NumPy: the linear
part of the dense depth map (SMoE §3.2, ablate.data.lidar.dense_depth).

Work buffers are kept between calls (per thread): on small virtual machines, faulting in the pages of freshly
allocated arrays costs more than the arithmetic done on them."""
from __future__ import annotations

import threading

import numpy as np

KEY = 65536.0
"""Vertex sort key y * KEY + x; exact in float64 for pixel coordinates below KEY."""


class Scratch(threading.local):
    """Named work buffers, grown on demand and reused by later calls of the same thread."""

    def __init__(self) -> None:
        self.buffers: dict[str, np.ndarray] = {}

    def __call__(self, name: str, shape: int | tuple[int, ...], dtype=np.float64) -> np.ndarray:
        shape = (shape,) if isinstance(shape, int) else shape
        n = int(np.prod(shape))
        buf = self.buffers.get(name)
        if buf is None or buf.dtype != dtype or buf.size < n:
            buf = self.buffers[name] = np.empty(n + n // 4 + 16, dtype)
        return buf[:n].reshape(shape)


scratch = Scratch()


def _segments(counts: np.ndarray, total: int, name: str) -> np.ndarray:
    """Segment number of each of `total` items laid out as consecutive segments of `counts` items (zeros allowed)."""
    idx = scratch(name, total + 1, np.intp)
    idx.fill(0)
    ends = scratch(name + ".ends", len(counts) - 1, np.intp)
    np.cumsum(counts[:-1], out=ends)
    np.add.at(idx, ends, 1)
    idx = idx[:total]
    return np.cumsum(idx, out=idx)


def _arange(n: int, name: str) -> np.ndarray:
    """0, 1, ..., n-1 as float64, kept between calls (read only)."""
    buf = scratch.buffers.get(name)
    if buf is None or buf.size < n:
        buf = scratch.buffers[name] = np.arange(n + n // 4 + 16, dtype=np.float64)
    return buf[:n]


def _vertices(tri: np.ndarray, flat: np.ndarray, w: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(3,T) x, y (float64) and value of the vertices, sorted top to bottom (then left to right)."""
    n = len(tri)
    v = scratch("tri.key", (3, n))
    np.multiply(tri[:, :, 1].T, KEY, out=v)
    v += tri[:, :, 0].T
    k = scratch("tri.sorted", (3, n))
    np.minimum(np.minimum(v[0], v[1], out=k[0]), v[2], out=k[0])
    np.maximum(np.maximum(v[0], v[1], out=k[2]), v[2], out=k[2])
    np.add(v[0], v[1], out=k[1])
    k[1] += v[2]
    k[1] -= k[0]
    k[1] -= k[2]
    y = scratch("tri.y", (3, n))
    np.floor(np.multiply(k, 1.0 / KEY, out=y), out=y)
    x = scratch("tri.x", (3, n))
    np.multiply(y, -KEY, out=x)
    x += k
    np.multiply(y, w, out=v)
    v += x
    lin = scratch("tri.lin", (3, n), np.intp)
    np.copyto(lin, v, casting="unsafe")
    z32 = scratch("tri.z32", (3, n), np.float32)
    np.take(flat, lin, out=z32)
    z = scratch("tri.z", (3, n))
    np.copyto(z, z32)
    return x, y, z


def _trapezoids(x: np.ndarray, y: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split each triangle (vertices sorted by y) into its upper (rows y0..y1-1) and lower (rows y1..y2-1) part.

    Returns (rows per part (2T,) intp, (8,2T) float64 table: edges x = il + sl*row and x = ir + sr*row (either
    may be the left one), plane z = a*x + b*row + c, first row)."""
    n = x.shape[1]
    (x0, x1, x2), (y0, y1, y2), (z0, z1, z2) = x, y, z
    f = scratch("tri.f", (9, n))
    dx1, dy1, dx2, dy2, det, dz1, dz2, t1, t2 = f
    np.subtract(x1, x0, out=dx1), np.subtract(y1, y0, out=dy1)
    np.subtract(x2, x0, out=dx2), np.subtract(y2, y0, out=dy2)
    np.subtract(np.multiply(dx1, dy2, out=det), np.multiply(dx2, dy1, out=t1), out=det)
    np.subtract(z1, z0, out=dz1), np.subtract(z2, z0, out=dz2)
    table = scratch("trap.table", (8, 2 * n))
    il, sl, ir, sr, a, b, c, r0 = table
    with np.errstate(divide="ignore", invalid="ignore"):  # det == 0 parts get no rows
        np.subtract(np.multiply(dz1, dy2, out=a[:n]), np.multiply(dz2, dy1, out=t1), out=a[:n])
        a[:n] /= det
        np.subtract(np.multiply(dx1, dz2, out=b[:n]), np.multiply(dx2, dz1, out=t1), out=b[:n])
        b[:n] /= det
        np.subtract(z0, np.multiply(a[:n], x0, out=t1), out=c[:n])
        c[:n] -= np.multiply(b[:n], y0, out=t1)
        a[n:], b[n:], c[n:] = a[:n], b[:n], c[:n]
        # Long edge 0-2 in (il, sl), short edges 0-1 (upper) and 1-2 (lower) in (ir, sr); which one is on the left
        # is decided per row by the rasteriser (the two do not cross inside a part).
        np.divide(dx2, dy2, out=sl[:n])
        sl[n:] = sl[:n]
        np.subtract(x0, np.multiply(y0, sl[:n], out=t1), out=il[:n])
        il[n:] = il[:n]
        np.divide(dx1, dy1, out=sr[:n])
        np.divide(np.subtract(x2, x1, out=t1), np.subtract(y2, y1, out=t2), out=sr[n:])
        np.subtract(x0, np.multiply(y0, sr[:n], out=t1), out=ir[:n])
        np.subtract(x1, np.multiply(y1, sr[n:], out=t1), out=ir[n:])
    r0[:n], r0[n:] = y0, y1
    nrows = scratch("trap.rows", 2 * n, np.intp)
    np.copyto(nrows[:n], dy1, casting="unsafe")
    np.copyto(nrows[n:], np.subtract(y2, y1, out=t1), casting="unsafe")
    flat = scratch("trap.flat", n, bool)
    np.equal(det, 0, out=flat)
    nrows[:n][flat] = 0
    nrows[n:][flat] = 0
    return nrows, table


def raster_triangles(tri: np.ndarray, flat: np.ndarray, w: int) -> tuple[np.ndarray, np.ndarray]:
    """Linear interpolation of `flat` (a flattened (H,W) map) inside triangles whose vertices are pixel centres.

    tri: (T,3,2) integer vertex (x, y) pixel coordinates inside the image. Fill rule: a pixel centre belongs to the
    triangle whose half-open span [left edge, right edge) on the pixel's row contains it, rows running from the
    top vertex (included) to the bottom vertex (excluded); pixels on an edge shared by two triangles are
    therefore drawn once. Returns (flat pixel indices (N,) intp, values (N,) float64), buffers reused by the next
    call of the same thread."""
    if len(tri) == 0:
        return np.zeros(0, np.intp), np.zeros(0)
    x, y, z = _vertices(tri, flat, w)
    nrows, (il, sl, ir, sr, a, b, c, r0) = _trapezoids(x, y, z)
    off = scratch("trap.off", len(nrows), np.intp)
    np.cumsum(nrows, out=off)
    off -= nrows
    r0 -= off  # row of span k of part t: r0[t] + k - off[t] = (r0 - off)[t] + global span number
    ns = int(off[-1] + nrows[-1])
    if ns == 0:
        return np.zeros(0, np.intp), np.zeros(0)
    t = _segments(nrows, ns, "span.part")
    row, xl, xr, at, v0, u, e2 = scratch("span.f", (7, ns))
    np.take(r0, t, out=row)
    row += _arange(ns, "arange.f")
    for e, i, s in ((xl, il, sl), (e2, ir, sr)):
        np.take(i, t, out=e)
        e += np.multiply(np.take(s, t, out=u), row, out=u)
    np.maximum(xl, e2, out=xr)
    np.minimum(xl, e2, out=xl)
    for e in (xl, xr):
        e -= 1e-9  # ceil of x, robust to rounding where the exact crossing is an integer
        np.ceil(e, out=e)
    cnt = scratch("span.count", ns, np.intp)
    np.copyto(cnt, np.subtract(xr, xl, out=xr), casting="unsafe")
    np.maximum(cnt, 0, out=cnt)
    np.take(a, t, out=at)
    np.multiply(at, xl, out=v0)
    v0 += np.multiply(np.take(b, t, out=u), row, out=u)
    v0 += np.take(c, t, out=u)
    q0 = scratch("span.first", ns, np.intp)
    np.cumsum(cnt, out=q0)
    q0 -= cnt
    npx = int(q0[-1] + cnt[-1])
    start = xr  # flat index of the span's first pixel, less its first output position
    np.multiply(row, w, out=start)
    start += xl
    start -= q0
    v0 -= np.multiply(at, q0, out=u)  # value at output position q: v0 + a * q
    s = _segments(cnt, npx, "px.span")
    q = _arange(npx, "arange.f")
    lin_f, val, tmp = scratch("px.f", (3, npx))
    np.add(np.take(start, s, out=lin_f), q, out=lin_f)
    lin = scratch("px.lin", npx, np.intp)
    np.copyto(lin, lin_f, casting="unsafe")
    np.multiply(np.take(at, s, out=val), q, out=val)
    val += np.take(v0, s, out=tmp)
    return lin, val
