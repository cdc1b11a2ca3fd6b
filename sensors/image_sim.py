"""Image-level rendering: exact rolling-shutter smear of stars, then the detector signal chain.

Star signal (electrons) of row ``r``, column ``c`` for a star of ``N`` electrons whose affected
image position at time ``t`` is ``(X(t), Y(t))``::

    E[r, c] = N / T * integral_{t0 + r ld}^{t0 + r ld + T} Px(c | X(t)) Py(r | Y(t)) dt
    Px(c | X) = Phi((c + 1/2 - X) / s) - Phi((c - 1/2 - X) / s)        (pixel-integrated Gaussian)

(``Phi`` the standard normal CDF, ``s`` the PSF sigma), i.e. each row integrates the moving PSF
over its *own* exposure window. The time integral uses the midpoint rule with ``K`` samples per
window, ``K = max(min_samples, ceil(path / max_step_px))`` so the star moves at most
``max_step_px`` between samples (for a uniform streak this under-estimates its variance by
``step^2 / 12``, 0.003 px^2 at 0.2 px). All (star, row, sample) attitudes are evaluated in one
vectorised call per chunk of stars and the sum over samples is an einsum.

A consequence worth knowing: with image velocity ``v_y`` along the columns the rows sample the
star at times shifted by ``r ld``, so the whole spot (PSF and streak) is scaled along y by
``1 / (1 - v_y ld)`` and its total signal is ``N / (1 - v_y ld)`` (0.3 % at 1 deg/s on he2021a).

Signal chain (:func:`digitise`): mean electrons = stars + (sky background + dark current) * T
+ hot-pixel dark current * T; Poisson shot noise; clip at the full well; Gaussian read noise;
divide by the gain, add the bias, round, clip to ``[0, 2^bits - 1]`` ADU.
"""
from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.special import ndtr, pdtr

from rollingstar.sensors.conventions import NS_PER_S
from rollingstar.sensors.scenario import ImageConfig

FOOTPRINT_SIGMAS = 6.0  # PSF half-width rendered around the streak (mass beyond: 2e-9)
CHUNK_ELEMENTS = 4_000_000  # (stars x rows x samples x columns) per vectorised chunk
COARSE_SAMPLES = 9  # samples of each star's track used to size its footprint
_DEFAULTS = ImageConfig()  # the defaults are the scenario's ``image`` section's, written there once


@dataclass(frozen=True)
class ImageModel:
    """Photometric and detector parameters of the image-level simulation.

    ``photons_per_s_mag0`` is the signal in electrons per second collected from a magnitude-0
    star (after optics transmission, aperture and quantum efficiency): a star of magnitude ``m``
    gives ``photons_per_s_mag0 * 10^(-0.4 m) * T`` electrons. Background and dark current are per
    pixel per second; ``gain_e_per_adu`` electrons make one ADU; ``bias_adu`` is the offset;
    ``hot_pixel_fraction`` of the pixels (fixed positions) have extra dark current
    ``hot_pixel_e_per_s``.
    """

    psf_sigma_px: float = _DEFAULTS.psf_sigma_px
    photons_per_s_mag0: float = _DEFAULTS.photons_per_s_mag0
    background_e_per_px_s: float = _DEFAULTS.background_e_per_px_s
    dark_e_per_px_s: float = _DEFAULTS.dark_e_per_px_s
    read_noise_e: float = _DEFAULTS.read_noise_e
    gain_e_per_adu: float = _DEFAULTS.gain_e_per_adu
    bias_adu: float = _DEFAULTS.bias_adu
    bit_depth: int = _DEFAULTS.bit_depth
    full_well_e: float = _DEFAULTS.full_well_e
    hot_pixel_fraction: float = _DEFAULTS.hot_pixel_fraction
    hot_pixel_e_per_s: float = _DEFAULTS.hot_pixel_e_per_s

    def __post_init__(self):
        positive = ("psf_sigma_px", "photons_per_s_mag0", "gain_e_per_adu", "full_well_e")
        non_negative = ("background_e_per_px_s", "dark_e_per_px_s", "read_noise_e", "bias_adu", "hot_pixel_e_per_s")
        for name in positive:
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"ImageModel.{name} must be finite and > 0, got {v!r}")
        for name in non_negative:
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"ImageModel.{name} must be finite and >= 0, got {v!r}")
        if not (isinstance(self.bit_depth, (int, np.integer)) and 1 <= self.bit_depth <= 16):
            raise ValueError(f"ImageModel.bit_depth must be an integer in [1, 16] (uint16 output), got {self.bit_depth!r}")
        if not (0.0 <= self.hot_pixel_fraction <= 1.0):
            raise ValueError(f"ImageModel.hot_pixel_fraction must be in [0, 1], got {self.hot_pixel_fraction!r}")

    def star_electrons(self, magnitude, exposure_ns: int) -> np.ndarray:
        """Expected signal electrons ``photons_per_s_mag0 * 10^(-0.4 m) * T``."""
        return self.photons_per_s_mag0 * 10.0 ** (-0.4 * np.asarray(magnitude, dtype=float)) * (exposure_ns / NS_PER_S)

    @property
    def max_adu(self) -> int:
        """Saturation level of the ADC, ``2^bit_depth - 1``."""
        return (1 << int(self.bit_depth)) - 1


# positions(star (m,) int indices into the frame's stars, t_ns (m,) int64, rows (m,) float: the
# detector row each sample is exposed by, for row-dependent time effects) -> (x, y)
PositionFn = Callable[[np.ndarray, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]


def _footprints(positions: PositionFn, timing, t0_ns: int, unit: np.ndarray, y_star: np.ndarray,
                pad: float, shape: tuple[int, int], max_step_px: float, min_samples: int):
    """Per-star row/column ranges (clipped to the detector) and sample counts.

    Pass 1 samples the track over the star's own window (row ``y_star``) to get its row extent;
    pass 2 re-samples over the union of the windows of all those rows (they start up to
    ``extent * ld`` apart), which bounds the footprint even for fast motion.
    """
    height, width = shape
    n = unit.shape[0]
    ld = timing.effective_line_delay_ns
    frac = np.linspace(0.0, 1.0, COARSE_SAMPLES)
    row_lo, row_hi = y_star, y_star
    for _ in range(2):
        start = t0_ns + np.rint(np.clip(row_lo - pad, -1.0, height) * ld)
        end = t0_ns + np.rint(np.clip(row_hi + pad, -1.0, height) * ld) + timing.exposure_ns
        t = np.rint(start[:, None] + (end - start)[:, None] * frac[None, :]).astype(np.int64)
        rows = np.repeat(np.clip(np.where(np.isfinite(y_star), y_star, 0.0), -1.0, height), COARSE_SAMPLES)
        x, y = positions(np.repeat(np.arange(n), COARSE_SAMPLES), t.reshape(-1), rows)
        x, y = x.reshape(n, -1), y.reshape(n, -1)
        row_lo, row_hi = np.min(y, axis=1), np.max(y, axis=1)
    col_lo, col_hi = np.min(x, axis=1), np.max(x, axis=1)
    # path travelled during one exposure (the per-row window), from the pass-2 track
    seg = np.hypot(np.diff(x, axis=1), np.diff(y, axis=1)).sum(axis=1)
    span = (end - start).astype(float)
    path = seg * timing.exposure_ns / np.maximum(span, 1.0)
    samples = np.maximum(min_samples, np.ceil(path / max_step_px)).astype(np.int64)
    r0 = np.clip(np.floor(row_lo - pad), 0, height - 1).astype(np.int64)
    r1 = np.clip(np.ceil(row_hi + pad), 0, height - 1).astype(np.int64)
    c0 = np.clip(np.floor(col_lo - pad), 0, width - 1).astype(np.int64)
    c1 = np.clip(np.ceil(col_hi + pad), 0, width - 1).astype(np.int64)
    on = (row_hi + pad >= 0) & (row_lo - pad <= height - 1) & (col_hi + pad >= 0) & (col_lo - pad <= width - 1)
    on &= np.isfinite(row_lo) & np.isfinite(row_hi) & np.isfinite(col_lo) & np.isfinite(col_hi)
    return r0, r1, c0, c1, samples, on


def render_star_electrons(positions: PositionFn, timing, shape: tuple[int, int], t0_ns: int, unit_icrs,
                          electrons, y_star, psf_sigma_px: float, max_step_px: float = 0.2,
                          min_samples: int = 8) -> np.ndarray:
    """Noise-free star signal (electrons, float (H, W)) of one frame, rolling-shutter exact.

    ``positions(star (m,) int, t_ns (m,) int64, rows (m,)) -> (x, y)`` gives affected image
    positions of stars ``star`` (indices into ``unit_icrs``) exposed by detector ``rows``;
    ``y_star`` are the stars' centroid rows (solution of the row equation) used to locate their
    footprints. See the module docstring for the integral being evaluated.
    """
    height, width = shape
    image = np.zeros(height * width)
    unit = np.asarray(unit_icrs, dtype=float).reshape(-1, 3)
    if unit.shape[0] == 0:
        return image.reshape(shape)
    electrons = np.broadcast_to(np.asarray(electrons, dtype=float), (unit.shape[0],))
    s = float(psf_sigma_px)
    pad = FOOTPRINT_SIGMAS * s + 1.0
    r0, r1, c0, c1, samples, on = _footprints(positions, timing, t0_ns, unit, np.asarray(y_star, dtype=float),
                                              pad, shape, max_step_px, min_samples)
    # work items: (star, block of rows), each at most CHUNK_ELEMENTS (rows x columns x samples)
    stars = np.flatnonzero(on & (electrons > 0))
    nrow, ncol = (r1 - r0 + 1)[stars], (c1 - c0 + 1)[stars]
    nblk = np.maximum(1, np.ceil(nrow * ncol * samples[stars] / CHUNK_ELEMENTS)).astype(np.int64)
    blk_rows = -(-nrow // nblk)
    item = np.repeat(np.arange(stars.size), nblk)
    j = np.arange(item.size) - np.repeat(np.cumsum(nblk) - nblk, nblk)
    star = stars[item]
    i_r0 = r0[star] + j * blk_rows[item]
    i_r1 = np.minimum(r1[star], i_r0 + blk_rows[item] - 1)
    cost = (i_r1 - i_r0 + 1) * ncol[item] * samples[star]
    order = np.argsort(cost, kind="stable")  # similar footprints share a chunk (less padding)
    ld = np.int64(timing.effective_line_delay_ns)
    start = 0
    while start < order.size:
        stop = start + 1
        while stop < order.size and (stop - start + 1) * cost[order[stop]] <= CHUNK_ELEMENTS:
            stop += 1
        it = order[start:stop]
        start = stop
        st = star[it]
        n_s = it.size
        n_r = int((i_r1[it] - i_r0[it]).max()) + 1
        n_c = int((c1[st] - c0[st]).max()) + 1
        n_k = int(samples[st].max())
        rows = i_r0[it, None] + np.arange(n_r)[None, :]  # (S, R)
        cols = c0[st, None] + np.arange(n_c)[None, :]  # (S, C)
        offsets = np.rint((np.arange(n_k) + 0.5) * (timing.exposure_ns / n_k)).astype(np.int64)  # midpoint rule
        t = np.int64(t0_ns) + rows[:, :, None] * ld + offsets[None, None, :]  # (S, R, K)
        x, y = positions(np.repeat(st, n_r * n_k), t.reshape(-1),
                         np.broadcast_to(rows[:, :, None], t.shape).reshape(-1).astype(float))
        x, y = x.reshape(n_s, n_r, n_k), y.reshape(n_s, n_r, n_k)
        py = ndtr((rows[:, :, None] + 0.5 - y) / s) - ndtr((rows[:, :, None] - 0.5 - y) / s)  # (S, R, K)
        edges = np.concatenate([cols - 0.5, cols[:, -1:] + 0.5], axis=1)  # (S, C + 1)
        cdf = ndtr((edges[:, None, None, :] - x[..., None]) / s)  # (S, R, K, C + 1)
        patch = np.einsum("srk,srkc->src", py, np.diff(cdf, axis=-1))
        patch *= (electrons[st] / n_k)[:, None, None]
        valid = (rows <= i_r1[it, None])[:, :, None] & (cols <= c1[st, None])[:, None, :]
        flat = np.minimum(rows, height - 1)[:, :, None] * width + np.minimum(cols, width - 1)[:, None, :]
        image += np.bincount(flat[valid], weights=patch[valid], minlength=height * width)
    return image.reshape(shape)


def hot_pixel_mask(shape: tuple[int, int], fraction: float, rng: np.random.Generator) -> np.ndarray:
    """Boolean (H, W) mask with ``round(fraction * H * W)`` hot pixels at positions drawn by ``rng``."""
    n_pix = shape[0] * shape[1]
    count = int(round(fraction * n_pix))
    mask = np.zeros(n_pix, dtype=bool)
    if count:
        mask[rng.choice(n_pix, size=count, replace=False)] = True
    return mask.reshape(shape)


def mean_electrons(star_e: np.ndarray, model: ImageModel, exposure_ns: int, hot_mask: np.ndarray | None) -> np.ndarray:
    """Expected electrons per pixel: stars + (background + dark) * T + hot-pixel dark * T."""
    t_s = exposure_ns / NS_PER_S
    out = star_e + (model.background_e_per_px_s + model.dark_e_per_px_s) * t_s
    if hot_mask is not None and model.hot_pixel_e_per_s > 0:
        out = out + hot_mask * (model.hot_pixel_e_per_s * t_s)
    return out


@functools.lru_cache(maxsize=16)
def _poisson_guide_table(lam: float):
    """Support ``k``, CDF ``F(k)``, per-bucket answer (float32) and crossed-bucket mask of Poisson(lam)."""
    half = 12.0 * np.sqrt(lam) + 40.0
    k = np.arange(max(0, int(np.floor(lam - half))), int(np.ceil(lam + half)) + 1)
    cdf = pdtr(k, lam)  # Poisson CDF P(X <= k)
    keep = cdf >= 2.0**-60  # drop the left tail (mass < 2^-60)
    k, cdf = k[keep], cdf[keep]
    n = int(np.searchsorted(cdf, 1.0)) + 1  # up to the first entry that rounds to 1
    k, cdf = k[:n], cdf[:n]
    nb = 1 << 16
    edges = np.arange(nb + 1) / nb
    lo = np.searchsorted(cdf, edges[:-1], side="right")  # answer index for the bucket's lowest u
    hi = np.searchsorted(cdf, np.nextafter(edges[1:], 0.0), side="right")  # ... and for its highest u
    value = k[np.minimum(lo, k.size - 1)].astype(np.float32)
    for arr in (k, cdf, value):
        arr.flags.writeable = False
    ambiguous = lo != hi
    ambiguous.flags.writeable = False
    return k, cdf, value, ambiguous


def poisson_constant(lam: float, size: int, rng: np.random.Generator) -> np.ndarray:
    """``size`` Poisson(``lam``) counts, float32 (integers, exact below 2^24), by table inversion.

    Inversion: ``k = min{k : F(k) > u}`` for ``u ~ U[0, 1)`` and ``F`` the Poisson CDF is exactly
    Poisson-distributed (Devroye 1986, *Non-Uniform Random Variate Generation*, sec. III.2). A guide
    table (Chen & Asau 1974) indexed by the top 16 bits of ``u`` gives the answer directly for
    every bucket of ``[0, 1)`` that no CDF step crosses; uniforms in a crossed bucket (at most
    ``len(F) / 2^16`` of them) get 53-bit precision (32 drawn bits + a fresh double for the rest)
    and a binary search on ``F``. ``F`` runs from ``2^-60`` to its first double equal to 1, so
    the tail mass left out is below ``2^-60``.

    Hand-written because numpy's ``Generator.poisson`` draws each count by a rejection loop (the
    multiplication method for ``lam < 10``): ~100 ms per 1M pixels here against ~10 ms for this
    (``rollingstar bench perf``, docs/performance.md). ``lam > 1e6`` falls back to numpy.
    """
    lam = float(lam)
    if lam <= 0.0:
        return np.zeros(size, dtype=np.float32)
    if lam > 1e6:
        return rng.poisson(lam, size).astype(np.float32)
    k, cdf, value, ambiguous = _poisson_guide_table(lam)
    bits = rng.integers(0, 1 << 32, size=size, dtype=np.uint32)  # u = bits / 2^32 (+ finer bits below)
    bucket = (bits >> np.uint32(16)).astype(np.intp)
    out = value[bucket]
    crossed = np.flatnonzero(ambiguous[bucket])
    if crossed.size:
        u = (bits[crossed] + rng.random(crossed.size)) / 2.0**32
        out[crossed] = k[np.minimum(np.searchsorted(cdf, u, side="right"), k.size - 1)]
    return out


def shot_noise(mean_e: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Poisson counts (float32) of per-pixel means ``mean_e``; same distribution as ``rng.poisson(mean_e)``.

    A sum of independent Poisson variables is Poisson with the summed mean, so with ``m0 =
    min(mean_e)`` (the sky + dark level shared by every pixel)::

        Poisson(mean_e) = Poisson(m0) + Poisson(mean_e - m0)

    The first term is drawn for every pixel at once by :func:`poisson_constant`, the second only
    where ``mean_e > m0`` (the stars' footprints and hot pixels; elsewhere it is exactly 0). Every
    pixel still gets its full shot noise; only the generator changed (exact, no approximation).
    """
    flat = np.asarray(mean_e, dtype=float).reshape(-1)
    if flat.size == 0:
        return np.zeros(np.shape(mean_e), dtype=np.float32)
    if not np.all(np.isfinite(flat)) or flat.min() < 0:
        raise ValueError("mean electrons must be finite and >= 0")
    m0 = float(flat.min())
    counts = poisson_constant(m0, flat.size, rng)
    excess = np.flatnonzero(flat > m0)
    if excess.size:
        counts[excess] += rng.poisson(flat[excess] - m0)
    return counts.reshape(np.shape(mean_e))


def digitise(mean_e: np.ndarray, model: ImageModel, rng_shot: np.random.Generator,
             rng_read: np.random.Generator) -> np.ndarray:
    """Shot noise, full-well clip, read noise, gain, bias, rounding and ADC clip -> uint16 ADU.

    Shot noise by :func:`shot_noise` (exact Poisson); read noise ``N(0, read_noise_e)`` drawn in
    float32 (``Generator.standard_normal(dtype=float32)``, 25 % faster than float64; the counts
    stay below the full well < 2^24, exact in float32, and float32's 6e-8 relative rounding of
    the sum is 1e-3 e at 20 000 e, far below the ADU step).
    """
    e = shot_noise(mean_e, rng_shot)
    np.minimum(e, np.float32(model.full_well_e), out=e)
    if model.read_noise_e > 0:
        noise = rng_read.standard_normal(size=e.shape, dtype=np.float32)
        noise *= np.float32(model.read_noise_e)
        e += noise
    e *= np.float32(1.0 / model.gain_e_per_adu)
    e += np.float32(model.bias_adu)
    np.rint(e, out=e)
    np.clip(e, 0, model.max_adu, out=e)
    return e.astype(np.uint16)
