"""Scanline rasterisation of triangles with linear (barycentric) interpolation, vectorised in NumPy: the linear
part of the dense depth map (SMoE §3.2, ablate.data.lidar.dense_depth).

Work buffers are kept between calls (per thread): on small virtual machines, faulting in the pages of freshly
allocated arrays costs more than the arithmetic done on them. Triangles are rasterised in blocks of at most SPANS
row spans and PIXELS pixels, so that the buffers stay small and in cache whatever the image; only the per-triangle
table grows with the input (about 4 MB for the ~40k triangles of a full-resolution KITTI frame)."""

from __future__ import annotations

import math
import threading

import numpy as np
from numpy.typing import DTypeLike

KEY = 65536
"""Vertex sort key y * KEY + x; exact for pixel coordinates below KEY."""
SPANS = 1 << 15
"""Row spans (one row of one triangle part) rasterised per block (more only for one part taller than that)."""
PIXELS = 1 << 15
"""Pixels written per block."""
TRIANGLES = 1 << 13
"""Triangles whose table is computed per block."""


class Scratch(threading.local):
    """Named work buffers, grown on demand and reused by later calls of the same thread."""

    def __init__(self) -> None:
        self.buffers: dict[str, np.ndarray] = {}

    def __call__(self, name: str, shape: int | tuple[int, ...], dtype: DTypeLike = np.float64) -> np.ndarray:
        shape = (shape,) if isinstance(shape, int) else shape
        n = math.prod(shape)
        buf = self.buffers.get(name)
        if buf is None or buf.dtype != dtype or buf.size < n:
            buf = self.buffers[name] = np.empty(n + n // 16 + 16, dtype)  # slack for the next, slightly larger frame
        return buf[:n].reshape(shape)

    def nbytes(self) -> int:
        """Bytes held by this thread's buffers."""
        return sum(b.nbytes for b in self.buffers.values())


scratch = Scratch()


def _segments(firsts: np.ndarray, total: int, name: str) -> np.ndarray:
    """Segment number of each of `total` items laid out as consecutive segments (empty ones allowed) whose first
    items are at positions `firsts` (non-decreasing, firsts[0] == 0)."""
    idx = scratch(name, total + 1, np.intp)
    idx.fill(0)
    np.add.at(idx, firsts[1:], 1)
    idx = idx[:total]
    return np.cumsum(idx, out=idx)


def _arange(n: int, dtype: DTypeLike, name: str) -> np.ndarray:
    """0, 1, ..., n-1, kept between calls (read only)."""
    buf = scratch.buffers.get(name)
    if buf is None or buf.size < n:
        buf = scratch.buffers[name] = np.arange(n + n // 16 + 16, dtype=dtype)
    return buf[:n]


def _take(a: np.ndarray, idx: np.ndarray, out: np.ndarray) -> np.ndarray:
    """out = a[idx] for indices known to be in range (mode="wrap" spares the buffered bounds check of "raise")."""
    return a.take(idx, out=out, mode="wrap")


def _table(tri: np.ndarray, flat: np.ndarray, w: int, j0: int, j1: int, f64: np.ndarray, i32: np.ndarray) -> None:
    """Fill columns j0:j1 of the per-triangle table: f64 (9,T) rows il, sl (long edge 0-2: x = il + sl * row),
    a, b, c (plane z = a x + b row + c), ir, sr of the short edge 0-1 (upper part), ir, sr of the short edge 1-2
    (lower part); i32 (4,T) rows y0, y1 (first row of the upper and lower part) and the row counts of the two parts
    (0 for a degenerate triangle). Vertices are sorted top to bottom, then left to right."""
    m = j1 - j0
    xy = scratch("tab.xy", (6, m))
    np.copyto(xy, tri[j0:j1].reshape(m, 6).T)
    key = scratch("tab.key", (3, m))
    np.multiply(xy[1::2], KEY, out=key)
    key += xy[0::2]
    k = scratch("tab.sorted", (3, m))
    np.minimum(np.minimum(key[0], key[1], out=k[0]), key[2], out=k[0])
    np.maximum(np.maximum(key[0], key[1], out=k[2]), key[2], out=k[2])
    np.add(key[0], key[1], out=k[1])
    k[1] += key[2]
    k[1] -= k[0]
    k[1] -= k[2]
    x, y = xy[:3], xy[3:]
    np.floor(np.multiply(k, 1.0 / KEY, out=y), out=y)
    np.subtract(k, np.multiply(y, KEY, out=x), out=x)
    lin = scratch("tab.lin", (3, m), np.intp)
    np.copyto(lin, np.add(np.multiply(y, w, out=key), x, out=key), casting="unsafe")
    z = scratch("tab.z", (3, m), np.float32)
    _take(flat, lin, z)
    (x0, x1, x2), (y0, y1, y2), (z0, z1, z2) = x, y, z
    f = scratch("tab.f", (9, m))
    dx1, dy1, dx2, dy2, det, dz1, dz2, t1, t2 = f
    np.subtract(x1, x0, out=dx1), np.subtract(y1, y0, out=dy1)
    np.subtract(x2, x0, out=dx2), np.subtract(y2, y0, out=dy2)
    np.subtract(np.multiply(dx1, dy2, out=det), np.multiply(dx2, dy1, out=t1), out=det)
    np.subtract(z1, z0, out=dz1, dtype=np.float64), np.subtract(z2, z0, out=dz2, dtype=np.float64)
    il, sl, a, b, c, iru, sru, irl, srl = f64[:, j0:j1]
    with np.errstate(divide="ignore", invalid="ignore"):  # degenerate triangles and flat parts get no rows
        np.subtract(np.multiply(dz1, dy2, out=a), np.multiply(dz2, dy1, out=t1), out=a)
        a /= det
        np.subtract(np.multiply(dx1, dz2, out=b), np.multiply(dx2, dz1, out=t1), out=b)
        b /= det
        np.subtract(z0, np.multiply(a, x0, out=t1), out=c, dtype=np.float64)
        c -= np.multiply(b, y0, out=t1)
        np.divide(dx2, dy2, out=sl)
        np.subtract(x0, np.multiply(y0, sl, out=t1), out=il)
        np.divide(dx1, dy1, out=sru)
        np.subtract(x0, np.multiply(y0, sru, out=t1), out=iru)
        np.divide(np.subtract(x2, x1, out=t1), np.subtract(y2, y1, out=t2), out=srl)
        np.subtract(x1, np.multiply(y1, srl, out=t1), out=irl)
    fy0, fy1, rows_u, rows_l = i32[:, j0:j1]
    np.copyto(fy0, y0, casting="unsafe")
    np.copyto(fy1, y1, casting="unsafe")
    np.copyto(rows_u, dy1, casting="unsafe")
    np.copyto(rows_l, t2, casting="unsafe")
    degenerate = np.equal(det, 0, out=scratch("tab.degenerate", m, bool))
    rows_u[degenerate] = 0
    rows_l[degenerate] = 0


def _spans(
    cum: np.ndarray,
    r0: np.ndarray,
    il: np.ndarray,
    sl: np.ndarray,
    ir: np.ndarray,
    sr: np.ndarray,
    a: np.ndarray,
    b: np.ndarray,
    c: np.ndarray,
    w: int,
    q_off: int,
    out: np.ndarray,
) -> int:
    """Rasterise one block of triangle parts (at most SPANS row spans in all) into `out`; cum: number of spans
    before each part and after the last (cumulative, from the start of the sweep), q_off: number of pixels drawn
    before this block. Returns the number of pixels drawn.

    A pixel's value is a * q + v0 with q its position in the drawing order of the whole call and v0 its span's
    value at q = 0."""
    ns = int(cum[-1] - cum[0])
    if ns == 0:
        return 0
    off = np.subtract(cum[:-1], cum[0], out=scratch("span.off", len(r0), np.intp))  # first span of each part
    t = _segments(off, ns, "span.part")
    rb = np.subtract(r0, off, out=scratch("span.r0", len(r0)), casting="unsafe")
    f = scratch("span.f", (6, ns))
    row, _, _, at, v0, _ = f
    _take(rb, t, row)
    row += _arange(ns, np.float64, "arange.f")
    xl, cnt, u = _span_columns(t, row, il, sl, ir, sr, f)
    q0 = scratch("span.first", ns + 1, np.intp)
    q0[0] = 0
    np.cumsum(cnt, out=q0[1:])
    npx = int(q0[-1])
    if npx == 0:
        return 0
    start = _span_planes(t, row, xl, q0, a, b, c, w, q_off, at, v0, u)
    _pixel_blocks(q0, start, at, v0, q_off, out)
    return npx


def _span_columns(
    t: np.ndarray,
    row: np.ndarray,
    il: np.ndarray,
    sl: np.ndarray,
    ir: np.ndarray,
    sr: np.ndarray,
    f: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """First column and pixel count of each span (between its part's two edges on its row), and the free work row
    of the span buffer ``f`` (rows row, xl, xr, at, v0, u)."""
    _, xl, xr, _, _, u = f
    for e, i, s in ((xl, il, sl), (xr, ir, sr)):
        _take(i, t, e)
        e += np.multiply(_take(s, t, u), row, out=u)
        e -= 1e-9  # ceil of x, robust to rounding where the exact crossing is an integer
        np.ceil(e, out=e)
    np.minimum(xl, xr, out=u)  # ceil(x - 1e-9) is monotonic: min/max commute with it
    np.maximum(xl, xr, out=xr)
    xl, u = u, xl
    cnt = scratch("span.count", len(row), np.intp)
    np.copyto(cnt, np.subtract(xr, xl, out=xr), casting="unsafe")
    return xl, cnt, u


def _span_planes(
    t: np.ndarray,
    row: np.ndarray,
    xl: np.ndarray,
    q0: np.ndarray,
    a: np.ndarray,
    b: np.ndarray,
    c: np.ndarray,
    w: int,
    q_off: int,
    at: np.ndarray,
    v0: np.ndarray,
    u: np.ndarray,
) -> np.ndarray:
    """Fill ``at`` and ``v0`` (each span's plane slope and value at q = 0, ``u`` a work row); returns the flat
    index of each span's first pixel, less its first position."""
    ns = len(row)
    _take(a, t, at)
    np.multiply(at, xl, out=v0)
    v0 += np.multiply(_take(b, t, u), row, out=u)
    v0 += _take(c, t, u)
    v0 -= np.multiply(at, np.add(q0[:ns], q_off, out=u), out=u)
    start = scratch("span.start", ns, np.intp)
    np.copyto(start, np.add(np.multiply(row, w, out=u), xl, out=u), casting="unsafe")
    start -= q0[:ns]
    return start


def _pixel_blocks(
    q0: np.ndarray, start: np.ndarray, at: np.ndarray, v0: np.ndarray, q_off: int, out: np.ndarray
) -> None:
    """Draw the spans' pixels in blocks of at most PIXELS (a span has fewer than KEY pixels)."""
    ns = len(start)
    s0 = 0
    while s0 < ns:
        p0 = int(q0[s0])
        s1 = max(int(np.searchsorted(q0, p0 + PIXELS, side="right")) - 1, s0 + 1)
        _pixels(q0[s0 : s1 + 1] - p0, start[s0:s1], at[s0:s1], v0[s0:s1], p0, q_off + p0, out)
        s0 = s1


def _pixels(
    q0: np.ndarray, start: np.ndarray, at: np.ndarray, v0: np.ndarray, p0: int, q_off: int, out: np.ndarray
) -> None:
    """out[start + q] = at * (q_off + q) + v0, span by span, for the q0[-1] pixels of consecutive spans (q0: first
    position of each span, then the total)."""
    npx = int(q0[-1])
    if npx == 0:
        return
    s = _segments(q0[:-1], npx, "px.span")
    lin = scratch("px.lin", npx, np.intp)
    np.add(_take(start, s, lin), _arange(npx, np.intp, "arange.i"), out=lin)
    if p0:
        lin += p0
    q, tmp = scratch("px.f", (2, npx))
    np.add(_arange(npx, np.float64, "arange.f"), q_off, out=q)
    np.multiply(_take(at, s, tmp), q, out=tmp)
    val = scratch("px.val", npx, out.dtype)
    np.add(tmp, _take(v0, s, q), out=val)
    out[lin] = val


def raster_triangles(tri: np.ndarray, flat: np.ndarray, w: int, out: np.ndarray) -> int:
    """Linear interpolation of `flat` (a flattened (H,W) map) inside triangles whose vertices are pixel centres,
    written into `out` (flattened (H,W), any float dtype; values are computed in float64 and rounded once).

    tri: (T,3,2) integer vertex (x, y) pixel coordinates inside the image. Fill rule: a pixel centre belongs to the
    triangle whose half-open span [left edge, right edge) on the pixel's row contains it, rows running from the
    top vertex (included) to the bottom vertex (excluded); pixels on an edge shared by two triangles are
    therefore drawn once. Pixels outside the triangles are left alone. Returns the number of pixels drawn."""
    n = len(tri)
    if n == 0:
        return 0
    f64 = scratch("tri.f", (9, n))
    i32 = scratch("tri.i", (4, n), np.int32)
    for j0 in range(0, n, TRIANGLES):
        _table(tri, flat, w, j0, min(j0 + TRIANGLES, n), f64, i32)
    il, sl, a, b, c, iru, sru, irl, srl = f64
    fy0, fy1, rows_u, rows_l = i32
    cum = scratch("tri.cumrows", n + 1, np.intp)
    cum[0] = 0
    drawn = 0
    # All upper parts in triangle order, then all lower parts: the drawing order that fixes a pixel's q.
    for rows, r0, ir, sr in ((rows_u, fy0, iru, sru), (rows_l, fy1, irl, srl)):
        np.cumsum(rows, out=cum[1:])
        j0 = 0
        while j0 < n:
            j1 = max(int(np.searchsorted(cum, cum[j0] + SPANS, side="right")) - 1, j0 + 1)
            part = slice(j0, j1)
            drawn += _spans(
                cum[j0 : j1 + 1],
                r0[part],
                il[part],
                sl[part],
                ir[part],
                sr[part],
                a[part],
                b[part],
                c[part],
                w,
                drawn,
                out,
            )
            j0 = j1
    return drawn
