"""Image Quilting (Efros & Freeman 2001) for multi-channel maps (PAPERS.md C, step 2).

The paper quilts maps of Fourier coefficients (22 channels at M = 10), not RGB, and
takes blocks only from inside one reflectance region. The algorithm, block by block in
raster order on a grid with step ``block_size - overlap``:

1. Overlap error of every candidate block: the sum of squared differences (over all
   channels) between the candidate and what is already on the canvas, in the left
   and/or top overlap strips. All candidates at once by FFT cross-correlation:
   SSD = Σ M S² - 2 Σ M S T + Σ M T², with M the overlap mask, T the canvas, S the
   source; the source's transform is computed once.
2. Pick uniformly among candidates whose error is within (1 + tolerance) of the best.
3. Paste along the minimum-error boundary cut (dynamic programming) through each
   overlap strip, so that the seam runs where the two blocks agree.

Candidates are the top-left corners of blocks lying *fully* inside the region mask.
:func:`random_tiling` places random candidates on the same grid with straight seams,
and :func:`seam_cost` measures how visible the seams are, to compare the two.

Example
-------
>>> cost = np.array([[5.0, 1.0, 5.0], [1.0, 5.0, 5.0], [5.0, 1.0, 5.0]])
>>> min_error_boundary_cut(cost).tolist()
[1, 0, 1]
"""

from __future__ import annotations

import numpy as np
from scipy import fft

from pipeline.core.errors import ConfigError


def min_error_boundary_cut(cost) -> np.ndarray:
    """Cheapest top-to-bottom path through an error surface (Efros & Freeman, §2.1).

    Each row contributes one pixel and consecutive rows' columns differ by at most one.

    Parameters
    ----------
    cost : array_like of shape (h, w)
        Non-negative per-pixel error, e.g. squared difference of two overlapping blocks.

    Returns
    -------
    path : ndarray of shape (h,), int
        Column of the path in each row; ties go to the lower column.
    """
    cost = np.asarray(cost, dtype=np.float64)
    if cost.ndim != 2 or min(cost.shape) < 1:
        raise ConfigError(f"cost must be a non-empty 2-D array, got shape {cost.shape}")
    if not np.all(np.isfinite(cost)):
        raise ConfigError("cost contains non-finite values")
    return _cut_kernel(cost)


def _cut_kernel(cost: np.ndarray) -> np.ndarray:
    height, width = cost.shape
    cumulative = np.empty_like(cost)
    cumulative[0] = cost[0]
    came_from = np.zeros((height, width), dtype=np.int64)
    columns = np.arange(width)
    for row in range(1, height):  # rows only: one vectorized step per row of the strip
        previous = cumulative[row - 1]
        # Neighbours j-1, j, j+1 with out-of-range ones at +inf; argmin picks the lowest.
        padded = np.concatenate([[np.inf], previous, [np.inf]])
        choices = np.stack([padded[:-2], padded[1:-1], padded[2:]])  # (3, w)
        best = choices.argmin(axis=0)
        came_from[row] = columns + best - 1
        cumulative[row] = cost[row] + choices[best, columns]
    path = np.empty(height, dtype=np.int64)
    path[-1] = int(cumulative[-1].argmin())
    for row in range(height - 1, 0, -1):
        path[row - 1] = came_from[row, path[row]]
    return path


def candidate_positions(mask, block_size: int) -> np.ndarray:
    """Top-left corners (row, col) of all blocks lying fully inside ``mask``.

    Parameters
    ----------
    mask : ndarray of shape (H, W), bool
    block_size : int

    Returns
    -------
    ndarray of shape (n, 2), int
    """
    mask = np.asarray(mask, dtype=bool)
    height, width = mask.shape
    if block_size > min(height, width):
        return np.zeros((0, 2), dtype=np.int64)
    # Summed-area table: the count of masked pixels in every block in O(H W).
    table = np.zeros((height + 1, width + 1), dtype=np.int64)
    table[1:, 1:] = mask.cumsum(0).cumsum(1)
    b = block_size
    counts = table[b:, b:] - table[:-b, b:] - table[b:, :-b] + table[:-b, :-b]
    return np.argwhere(counts == b * b)


def _check_settings(source, out_shape, block_size, overlap, mask, rng, tolerance=0.0):
    if not isinstance(rng, np.random.Generator):
        raise ConfigError(f"rng must be a numpy.random.Generator, got {rng!r}")
    source = np.asarray(source, dtype=np.float64)
    if source.ndim == 2:
        source = source[..., None]
    if source.ndim != 3:
        raise ConfigError(f"source must have shape (H, W, C), got {source.shape}")
    if not np.all(np.isfinite(source)):
        raise ConfigError("source contains non-finite values")
    height, width, _ = source.shape
    if isinstance(block_size, bool) or int(block_size) != block_size or block_size < 2:
        raise ConfigError(f"block_size must be an integer >= 2, got {block_size!r}")
    if block_size > min(height, width):
        raise ConfigError(f"block_size={block_size} exceeds the source size {height}x{width}")
    if int(overlap) != overlap or not 0 <= overlap < block_size:
        raise ConfigError(
            f"overlap must be an integer in [0, block_size={block_size}), got {overlap!r}"
        )
    if not np.isfinite(tolerance) or tolerance < 0:
        raise ConfigError(f"tolerance must be >= 0, got {tolerance!r}")
    out_shape = tuple(int(n) for n in out_shape)
    if len(out_shape) != 2 or min(out_shape) < 1:
        raise ConfigError(f"out_shape must be (H, W) with H, W >= 1, got {out_shape!r}")
    if mask is None:
        mask = np.ones((height, width), dtype=bool)
    mask = np.asarray(mask, dtype=bool)
    if mask.shape != (height, width):
        raise ConfigError(f"mask {mask.shape} does not match the source {(height, width)}")
    positions = candidate_positions(mask, int(block_size))
    if len(positions) == 0:
        raise ConfigError(
            f"no {block_size}x{block_size} block lies fully inside the region mask "
            f"({int(mask.sum())} pixels): use a smaller block_size"
        )
    return source, out_shape, int(block_size), int(overlap), positions


def _output_dtype(source) -> np.dtype:
    """float64 stays float64 (e.g. coefficient maps); everything else becomes float32."""
    return np.dtype(np.float64 if np.asarray(source).dtype == np.float64 else np.float32)


def _grid(out_shape, block_size, overlap):
    """Top-left corners of output blocks and the canvas size that holds them."""
    step = block_size - overlap
    counts = [max(1, -(-(n - overlap) // step)) for n in out_shape]
    canvas = tuple(c * step + overlap for c in counts)
    return [(i * step, j * step) for i in range(counts[0]) for j in range(counts[1])], canvas


class OverlapSearch:
    """All-candidate overlap SSD by FFT cross-correlation against a fixed source."""

    def __init__(self, source: np.ndarray, block_size: int, overlap: int):
        self.shape = source.shape[:2]
        self.source_fft = fft.rfft2(source, axes=(0, 1), workers=-1)  # (H, W', C)
        energy_fft = fft.rfft2((source**2).sum(axis=-1), workers=-1)
        self.masks, self.masked_energy = {}, {}
        for left in (False, True):
            for top in (False, True):
                overlap_mask = np.zeros((block_size, block_size))
                if left:
                    overlap_mask[:, :overlap] = 1.0
                if top:
                    overlap_mask[:overlap, :] = 1.0
                self.masks[left, top] = overlap_mask
                self.masked_energy[left, top] = self._correlate(energy_fft, overlap_mask)

    def _correlate(self, signal_fft: np.ndarray, kernel: np.ndarray) -> np.ndarray:
        """Σ_ab signal[y + a, x + b] kernel[a, b] for all (y, x) (circular; the valid
        corners never wrap)."""
        kernel_fft = fft.rfft2(kernel, s=self.shape, axes=(0, 1), workers=-1)
        product = signal_fft * np.conj(kernel_fft)
        if kernel.ndim == 3:  # multi-channel: correlate per channel, sum in frequency
            product = product.sum(axis=-1)
        return fft.irfft2(product, s=self.shape, workers=-1)

    def errors(self, template: np.ndarray, left: bool, top: bool) -> np.ndarray:
        """Overlap SSD, shape (H, W), for every top-left corner (valid ones meaningful)."""
        overlap_mask = self.masks[left, top]
        masked = template * overlap_mask[..., None]
        cross = self._correlate(self.source_fft, masked)
        constant = float((masked * template).sum())
        return np.maximum(self.masked_energy[left, top] - 2.0 * cross + constant, 0.0)


def _paste_with_cut(canvas, patch, y0, x0, overlap, left, top):
    """Write ``patch`` into ``canvas`` behind minimum-error cuts through the overlaps."""
    size = patch.shape[0]
    existing = canvas[y0 : y0 + size, x0 : x0 + size]
    error = ((patch - existing) ** 2).sum(axis=-1)  # (B, B)
    take_new = np.ones((size, size), dtype=bool)
    if left and overlap:
        path = _cut_kernel(error[:, :overlap])  # one column per row
        take_new[:, :overlap] &= np.arange(overlap)[None, :] >= path[:, None]
    if top and overlap:
        path = _cut_kernel(error[:overlap, :].T)  # one row per column
        take_new[:overlap, :] &= np.arange(overlap)[:, None] >= path[None, :]
    canvas[y0 : y0 + size, x0 : x0 + size] = np.where(take_new[..., None], patch, existing)


def quilt(
    source,
    out_shape,
    block_size: int = 32,
    overlap: int = 8,
    tolerance: float = 0.1,
    rng: np.random.Generator | None = None,
    mask=None,
    return_positions: bool = False,
):
    """Synthesize a larger map from ``source`` by Image Quilting.

    Parameters
    ----------
    source : ndarray of shape (H, W, C) or (H, W)
        E.g. a Fourier-coefficient map flattened to C = 3 (2M + 2) channels.
    out_shape : (int, int)
        (H_out, W_out) of the result.
    block_size : int
        Side of the square blocks (E&F suggest about the size of the texture's motifs).
    overlap : int
        Width of the overlap strips, 0 <= overlap < block_size (E&F: block_size / 6).
    tolerance : float
        Candidates with overlap error <= (1 + tolerance) * best are equally likely.
    rng : numpy.random.Generator
        The only source of randomness.
    mask : ndarray of shape (H, W), bool, optional
        The region: only blocks fully inside it are candidates.
    return_positions : bool
        Also return the source corner chosen for each output block.

    Returns
    -------
    output : ndarray of shape (H_out, W_out, C) (C = 1 for 2-D input)
        float64 for float64 input, float32 otherwise.
    positions : ndarray of shape (n_blocks, 2), int, only with ``return_positions``
    """
    out_dtype = _output_dtype(source)
    source, out_shape, block_size, overlap, candidates = _check_settings(
        source, out_shape, block_size, overlap, mask, rng, tolerance
    )
    search = OverlapSearch(source, block_size, overlap)
    corners, canvas_shape = _grid(out_shape, block_size, overlap)
    canvas = np.zeros((*canvas_shape, source.shape[2]))
    chosen = np.empty((len(corners), 2), dtype=np.int64)
    for index, (y0, x0) in enumerate(corners):
        left, top = x0 > 0, y0 > 0
        if (left or top) and overlap:
            template = canvas[y0 : y0 + block_size, x0 : x0 + block_size]
            errors = search.errors(template, left, top)[candidates[:, 0], candidates[:, 1]]
            best = errors.min()
            # The absolute slack absorbs FFT round-off when the best match is exact.
            slack = 1e-9 * (1.0 + float(np.abs(template).max()) ** 2)
            pool = np.flatnonzero(errors <= (1.0 + tolerance) * best + slack)
        else:
            pool = np.arange(len(candidates))
        sy, sx = candidates[pool[rng.integers(len(pool))]]
        chosen[index] = sy, sx
        patch = source[sy : sy + block_size, sx : sx + block_size]
        _paste_with_cut(canvas, patch, y0, x0, overlap, left, top)
    output = canvas[: out_shape[0], : out_shape[1]].astype(out_dtype)
    return (output, chosen) if return_positions else output


def random_tiling(
    source,
    out_shape,
    block_size: int = 32,
    overlap: int = 8,
    rng: np.random.Generator | None = None,
    mask=None,
) -> np.ndarray:
    """Baseline: random candidate blocks on the quilting grid, pasted with straight seams.

    Each block simply covers the overlap strips of its predecessors (E&F Fig. 2a with
    the same block grid as :func:`quilt`), so the comparison isolates the search and
    the cut.

    Parameters and returns as :func:`quilt` (without tolerance).
    """
    out_dtype = _output_dtype(source)
    source, out_shape, block_size, overlap, candidates = _check_settings(
        source, out_shape, block_size, overlap, mask, rng
    )
    corners, canvas_shape = _grid(out_shape, block_size, overlap)
    canvas = np.zeros((*canvas_shape, source.shape[2]))
    for y0, x0 in corners:
        sy, sx = candidates[rng.integers(len(candidates))]
        patch = source[sy : sy + block_size, sx : sx + block_size]
        canvas[y0 : y0 + block_size, x0 : x0 + block_size] = patch
    return canvas[: out_shape[0], : out_shape[1]].astype(out_dtype)


def seam_cost(output, block_size: int, overlap: int, reference=None) -> float:
    """How visible the block seams are: squared neighbour differences in overlap strips.

    The mean, over all neighbouring pixel pairs that straddle or lie inside an overlap
    strip of the block grid (where either method puts its seams), of the squared
    difference summed over channels. With ``reference`` (the source), it is divided by
    the same mean over all neighbouring pairs of the reference, so 1 means "as smooth
    as the source texture" and larger means visible seams.

    Parameters
    ----------
    output : ndarray of shape (H, W, C) or (H, W)
    block_size, overlap : int
        The grid used to make ``output``.
    reference : ndarray of shape (h, w, C), optional
    """
    output = np.asarray(output, dtype=np.float64)
    if output.ndim == 2:
        output = output[..., None]
    if output.ndim != 3:
        raise ConfigError(f"output must have shape (H, W, C), got {output.shape}")
    if int(block_size) != block_size or not 0 <= overlap < block_size:
        raise ConfigError(f"need 0 <= overlap={overlap} < block_size={block_size}")
    height, width, _ = output.shape
    dx, dy = _neighbour_differences(output)
    seam_cols = _seam_pairs(width, block_size - overlap, overlap)
    seam_rows = _seam_pairs(height, block_size - overlap, overlap)
    values = np.concatenate([dx[:, seam_cols].ravel(), dy[seam_rows].ravel()])
    if values.size == 0:
        raise ConfigError(
            f"an output of {height}x{width} has no seams for block_size="
            f"{block_size}, overlap={overlap}"
        )
    cost = float(values.mean())
    if reference is not None:
        reference = np.asarray(reference, dtype=np.float64)
        if reference.ndim == 2:
            reference = reference[..., None]
        if reference.ndim != 3 or reference.shape[2] != output.shape[2]:
            raise ConfigError(f"reference {reference.shape} must be (h, w, {output.shape[2]})")
        ref_dx, ref_dy = _neighbour_differences(reference)
        baseline = float(np.concatenate([ref_dx.ravel(), ref_dy.ravel()]).mean())
        cost /= max(baseline, 1e-300)
    return cost


def _neighbour_differences(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Squared differences summed over channels of the pairs (x, x+1), shape (H, W-1), and
    (y, y+1), shape (H-1, W), of an (H, W, C) image."""
    dx = ((image[:, 1:] - image[:, :-1]) ** 2).sum(axis=-1)
    dy = ((image[1:] - image[:-1]) ** 2).sum(axis=-1)
    return dx, dy


def _seam_pairs(length: int, step: int, overlap: int) -> np.ndarray:
    """Which of the ``length - 1`` neighbour pairs (x, x+1) touch an overlap strip: x in
    [x0 - 1, x0 + overlap - 1] for each seam at x0 = step, 2 step, ..."""
    pairs = np.zeros(length - 1, dtype=bool)
    for x0 in range(step, length, step):
        pairs[max(x0 - 1, 0) : min(x0 + overlap, length - 1)] = True
    return pairs
