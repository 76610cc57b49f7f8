"""Level-set grids as JAX functions: periodic linear and cubic B-spline interpolation.

Grid convention: node-centred periodic grid over the box [0, Lx) x [0, Ly) (x [0, Lz)); sample i
along an axis sits at x = i * L / n, i = 0 .. n-1 (no duplicated last node, wrap-around).
``values[i, j(, k)]`` has i along x (axis 0), j along y, k along z.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .._periodic import wrap

_MIN_SAMPLES = 4  # the cubic stencil is 4 wide: fewer samples would alias the periodic kernel
_SPACING_RTOL = 1e-6
_ORDERS = ("linear", "cubic")


class LevelSetGrid(eqx.Module):
    """Samples of a level-set function phi (negative inside) on a periodic node-centred grid.

    Build it with :func:`make_levelset_grid`, which validates raw input; the constructor only runs
    cheap shape checks so that the module can be rebuilt inside JAX transformations.

    Attributes:
        values: (nx, ny) or (nx, ny, nz) samples, ``values[i, j, k] = phi(i*hx, j*hy, k*hz)``.
        box: (Lx, Ly[, Lz]) periodic cell lengths (static).

    Example:
        >>> grid = make_levelset_grid(np.zeros((16, 16)), box=(1.0, 1.0))
        >>> grid.spacing
        (0.0625, 0.0625)
    """

    values: Float[Array, "..."]
    box: tuple[float, ...] = eqx.field(static=True, converter=lambda b: tuple(float(x) for x in b))

    def __check_init__(self):
        ndim = getattr(self.values, "ndim", None)
        if ndim not in (2, 3):
            raise ValueError(f"LevelSetGrid expected values of rank 2 or 3, got rank {ndim}.")
        if len(self.box) != ndim:
            raise ValueError(
                f"LevelSetGrid expected box of length {ndim} (one length per axis), got {self.box}."
            )
        if not all(np.isfinite(b) and b > 0 for b in self.box):
            raise ValueError(f"LevelSetGrid expected positive finite box lengths, got {self.box}.")

    @property
    def dim(self) -> int:
        """Spatial dimension (2 or 3)."""
        return self.values.ndim

    @property
    def shape(self) -> tuple[int, ...]:
        """Samples per axis, (nx, ny[, nz])."""
        return tuple(int(n) for n in self.values.shape)

    @property
    def spacing(self) -> tuple[float, ...]:
        """Grid step per axis, L_i / n_i."""
        return tuple(L / n for L, n in zip(self.box, self.shape))

    def coordinates(self) -> np.ndarray:
        """Node positions as a NumPy array of shape (*shape, dim); node i sits at i * L / n."""
        axes = [np.arange(n) * (L / n) for n, L in zip(self.shape, self.box)]
        return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)


def _default_dtype():
    return jnp.float64 if jax.config.jax_enable_x64 else jnp.float32


def _validate_box(box, ndim: int, shape: tuple[int, ...]) -> tuple[float, ...]:
    if box is None:
        return (1.0,) * ndim
    try:
        box_arr = np.asarray(box, dtype=float)
    except (TypeError, ValueError) as err:
        raise ValueError(
            f"make_levelset_grid expected box as {ndim} positive lengths, got {box!r}. "
            "Hint: pass e.g. box=(1.0,) * values.ndim."
        ) from err
    if box_arr.shape != (ndim,):
        raise ValueError(
            f"make_levelset_grid expected box of length {ndim} (one length per axis of a rank-{ndim} "
            f"array), got shape {box_arr.shape} ({box!r}). Hint: pass one length per array axis."
        )
    if not np.all(np.isfinite(box_arr)) or np.any(box_arr <= 0):
        raise ValueError(
            f"make_levelset_grid expected positive finite box lengths, got {tuple(box_arr.tolist())}. "
            "Hint: the box is the periodic cell [0, L_i) along each axis, L_i > 0."
        )
    spacing = box_arr / np.asarray(shape, dtype=float)
    spread = (spacing.max() - spacing.min()) / spacing.max()
    if spread > _SPACING_RTOL:
        raise ValueError(
            "make_levelset_grid expected equal grid spacing L_i/n_i on every axis (non-cubic "
            f"spacing mismatch): box {tuple(box_arr.tolist())} over shape {shape} gives spacing "
            f"{tuple(spacing.tolist())}. Hint: pass a box matching the array shape, e.g. "
            f"box={tuple(float(n * spacing.min()) for n in shape)}."
        )
    return tuple(float(b) for b in box_arr)


def make_levelset_grid(
    values: ArrayLike, box: Sequence[float] | None = None, *, dtype=None
) -> LevelSetGrid:
    """Validate raw samples and wrap them in a :class:`LevelSetGrid`.

    Args:
        values: (nx, ny) or (nx, ny, nz) real samples of phi, negative inside, every axis >= 4.
            A JAX tracer is accepted (shape checks only), so the grid can be built under jax.grad.
        box: periodic cell lengths (Lx, Ly[, Lz]); None -> unit square / cube. The spacing L_i/n_i
            must be the same on every axis (to 1e-6 relative).
        dtype: floating dtype of the stored values; default float64 if jax x64 is on, else float32.

    Returns:
        The validated grid.

    Raises:
        ValueError: non-numeric, wrong rank, empty, too few samples, NaN/inf, bad box, or unequal
            spacing; the message says what was expected, what arrived and a hint.

    Example:
        >>> x = np.arange(32) / 32
        >>> phi = np.hypot(*np.meshgrid(x - 0.5, x - 0.5, indexing="ij")) - 0.25
        >>> grid = make_levelset_grid(phi)
    """
    if isinstance(values, jax.core.Tracer):
        raw = None
        shape = tuple(values.shape)
        if not jnp.issubdtype(values.dtype, jnp.number) or jnp.iscomplexobj(values):
            raise ValueError(f"make_levelset_grid expected real numeric values, got {values.dtype}.")
    else:
        try:
            raw = np.asarray(values)
        except Exception as err:  # ragged lists, arbitrary objects
            raise ValueError(
                f"make_levelset_grid expected a real numeric array, got {type(values).__name__} "
                "that NumPy cannot convert. Hint: pass a 2D or 3D NumPy array of phi samples."
            ) from err
        if raw.dtype.kind not in "biuf":
            raise ValueError(
                f"make_levelset_grid expected a real numeric array, got dtype {raw.dtype}. "
                "Hint: pass float samples of the level-set function phi."
            )
        shape = raw.shape
    if len(shape) not in (2, 3):
        raise ValueError(
            f"make_levelset_grid expected a 2D or 3D array of samples, got rank {len(shape)} "
            f"(shape {shape}). Hint: one array axis per spatial axis, values[i, j(, k)]."
        )
    if 0 in shape:
        raise ValueError(
            f"make_levelset_grid expected a non-empty array, got shape {shape}. "
            "Hint: sample phi on at least 4 nodes per axis."
        )
    if min(shape) < _MIN_SAMPLES:
        raise ValueError(
            f"make_levelset_grid expected at least {_MIN_SAMPLES} samples per axis, got shape {shape}. "
            "Hint: resample phi on a finer grid (the cubic stencil is 4 nodes wide)."
        )
    if raw is not None and not np.all(np.isfinite(raw)):
        n_bad = int(np.size(raw) - np.count_nonzero(np.isfinite(raw)))
        raise ValueError(
            f"make_levelset_grid expected finite values, got {n_bad} NaN/inf samples. "
            "Hint: fill missing samples (e.g. with a large positive distance) before meshing."
        )
    box_t = _validate_box(box, len(shape), shape)
    if dtype is None:
        dtype = _default_dtype()
    elif not jnp.issubdtype(dtype, jnp.floating):
        raise ValueError(f"make_levelset_grid expected a floating dtype, got {dtype}.")
    data = values if raw is None else raw
    return LevelSetGrid(values=jnp.asarray(data, dtype=dtype), box=box_t)


def _prepare(values, box, points) -> tuple[Array, Array, Array]:
    """Shape checks (static, so they run before/while tracing) and common dtype."""
    values = jnp.asarray(values)
    d = values.ndim
    box_shape = (len(box),) if isinstance(box, (tuple, list)) else jnp.shape(box)
    if box_shape != (d,):
        raise ValueError(
            f"expected box with {d} lengths for rank-{d} values, got shape {box_shape}. "
            "Hint: one box length per grid axis."
        )
    points = jnp.asarray(points)
    if points.ndim < 1 or points.shape[-1] != d:
        raise ValueError(
            f"expected points of shape (m, {d}), got {points.shape}. "
            f"Hint: the last axis holds the {d} coordinates."
        )
    if not jnp.issubdtype(values.dtype, jnp.floating):
        values = values.astype(_default_dtype())
    dtype = jnp.result_type(values.dtype, points.dtype)
    if not jnp.issubdtype(dtype, jnp.floating):
        dtype = values.dtype
    return values.astype(dtype), jnp.asarray(box, dtype=dtype), points.astype(dtype)


# jitted (shapes, stencil and weights static) so that eager calls compile once instead of
# dispatching every small op; inside an outer jit it inlines
@functools.partial(jax.jit, static_argnames=("offsets", "weights_fn"))
def _tensor_interpolate(values, box, points, offsets, weights_fn) -> Array:
    """Separable stencil interpolation on a periodic grid.

    For each axis a, the grid coordinate t_a = wrap(x_a) / h_a splits into a base index floor(t_a)
    and a fraction f_a; the stencil nodes are base + offsets (mod n_a) with 1D weights
    weights_fn(f_a) of shape (..., len(offsets)). The tensor-product stencil is gathered at once
    (shape (m, s, s[, s])) and contracted axis by axis.
    """
    d = values.ndim
    shape = values.shape
    batch = points.shape[:-1]
    points = points.reshape(-1, d)
    n = jnp.asarray(shape, dtype=points.dtype)
    t = wrap(points, box) * (n / box)  # grid coordinate in [0, n]
    base = jnp.floor(t)
    frac = t - base  # floor has zero derivative: d frac / d x = 1 / h
    base = base.astype(jnp.int32)
    offs = jnp.asarray(offsets, dtype=jnp.int32)
    s = len(offsets)
    idx = []
    for a in range(d):  # loop over axes (2 or 3), not over points
        ia = (base[:, a : a + 1] + offs) % shape[a]  # (m, s)
        idx.append(ia.reshape((-1,) + (1,) * a + (s,) + (1,) * (d - 1 - a)))
    stencil = values[tuple(idx)]  # (m, s, ..., s)
    for a in range(d):
        w = weights_fn(frac[:, a])  # (m, s)
        stencil = jnp.einsum("ms...,ms->m...", stencil, w, precision=jax.lax.Precision.HIGHEST)
    return stencil.reshape(batch)


def _linear_weights(f: Array) -> Array:
    return jnp.stack([1.0 - f, f], axis=-1)


def _cubic_weights(f: Array) -> Array:
    # uniform cubic B-spline basis for nodes base-1, base, base+1, base+2
    f2 = f * f
    f3 = f2 * f
    g = 1.0 - f
    return jnp.stack(
        [g * g * g, 3.0 * f3 - 6.0 * f2 + 4.0, -3.0 * f3 + 3.0 * f2 + 3.0 * f + 1.0, f3], axis=-1
    ) / 6.0


def interpolate_linear(
    values: Float[ArrayLike, "..."], box: Sequence[float], points: Float[ArrayLike, "m d"]
) -> Float[Array, " m"]:
    """Periodic multilinear interpolation of grid samples (pure JAX, jit- and grad-able).

    Args:
        values: (nx, ny[, nz]) samples on the node-centred periodic grid.
        box: (d,) cell lengths.
        points: (m, d) query points; points outside [0, L) wrap periodically.

    Returns:
        (m,) interpolated values (a point batch (..., d) gives (...)).

    Example:
        >>> interpolate_linear(jnp.eye(4), (1.0, 1.0), jnp.array([[0.125, 0.0]]))  # -> [0.5]
    """
    values, box, points = _prepare(values, box, points)
    return _tensor_interpolate(values, box, points, (0, 1), _linear_weights)


def _periodic_kernel_hat(n: int, dtype) -> Array:
    # DFT of the periodic kernel [1/6, 4/6, 1/6]: (4 + 2 cos(2 pi k / n)) / 6 >= 1/3, never zero
    k = jnp.arange(n // 2 + 1, dtype=dtype)
    return (4.0 + 2.0 * jnp.cos(2.0 * jnp.pi * k / n)) / 6.0


def bspline_coefficients(values: Float[ArrayLike, "..."]) -> Float[Array, "..."]:
    """Periodic cubic B-spline prefilter: coefficients c whose spline interpolates the samples.

    Solves (c[i-1] + 4 c[i] + c[i+1]) / 6 = v[i] (periodic) along each axis in turn, exactly, by
    dividing by the kernel's DFT. Pure JAX, differentiable w.r.t. values.

    Args:
        values: (nx, ny[, nz]) samples (any rank >= 1 works; each axis is filtered).

    Returns:
        Coefficients of the same shape, for :func:`interpolate_cubic`.
    """
    c = jnp.asarray(values)
    if not jnp.issubdtype(c.dtype, jnp.floating):
        c = c.astype(_default_dtype())
    return _prefilter(c)


@jax.jit
def _prefilter(c: Array) -> Array:
    for a in range(c.ndim):
        n = c.shape[a]
        kernel = _periodic_kernel_hat(n, c.dtype)
        kernel = kernel.reshape((-1,) + (1,) * (c.ndim - 1 - a))
        c = jnp.fft.irfft(jnp.fft.rfft(c, axis=a) / kernel, n=n, axis=a).astype(c.dtype)
    return c


def interpolate_cubic(
    coefficients: Float[ArrayLike, "..."], box: Sequence[float], points: Float[ArrayLike, "m d"]
) -> Float[Array, " m"]:
    """Periodic C2 cubic B-spline interpolant from prefiltered coefficients (pure JAX).

    Args:
        coefficients: (nx, ny[, nz]) from :func:`bspline_coefficients`.
        box: (d,) cell lengths.
        points: (m, d) query points; points outside [0, L) wrap periodically.

    Returns:
        (m,) interpolated values. jax.grad / jax.hessian w.r.t. points are exact for the spline.

    Example:
        >>> c = bspline_coefficients(values)
        >>> phi = interpolate_cubic(c, (1.0, 1.0, 1.0), points)
    """
    coefficients, box, points = _prepare(coefficients, box, points)
    return _tensor_interpolate(coefficients, box, points, (-1, 0, 1, 2), _cubic_weights)


def _check_order(order: str) -> None:
    if order not in _ORDERS:
        raise ValueError(
            f"expected order 'linear' or 'cubic', got {order!r}. "
            "Hint: 'cubic' is C2 (curvatures), 'linear' matches marching cubes."
        )


def interpolate(
    grid: LevelSetGrid, points: Float[ArrayLike, "m d"], order: Literal["linear", "cubic"] = "linear"
) -> Float[Array, " m"]:
    """Evaluate a level-set grid at points (periodic); differentiable w.r.t. grid.values and points.

    Args:
        grid: the level-set grid.
        points: (m, d) query points.
        order: "linear" (multilinear) or "cubic" (C2 B-spline; prefilters on every call).

    Returns:
        (m,) values of phi.
    """
    _check_order(order)
    if order == "linear":
        return interpolate_linear(grid.values, grid.box, points)
    return interpolate_cubic(bspline_coefficients(grid.values), grid.box, points)


def grid_phi_fn(
    grid: LevelSetGrid, order: Literal["linear", "cubic"] = "cubic"
) -> Callable[[Array], Array]:
    """A level-set callable phi_fn(points (m, d)) -> (m,) for a grid; the prefilter runs once here.

    Args:
        grid: the level-set grid.
        order: "cubic" (default, C2: normals and curvatures) or "linear".

    Returns:
        A jit-able callable, differentiable w.r.t. points. It is a ``jax.tree_util.Partial``: a
        hashable function for ``jax.jit(phi_fn)`` and also a PyTree, so passed as an argument to a
        jitted function its data is traced, not baked in. To differentiate w.r.t. the grid values,
        call :func:`interpolate` with the grid as an argument.

    Example:
        >>> phi_fn = grid_phi_fn(grid)
        >>> normals = jax.vmap(jax.grad(lambda x: phi_fn(x[None])[0]))(points)
    """
    _check_order(order)
    if order == "linear":
        return jax.tree_util.Partial(interpolate_linear, grid.values, grid.box)
    return jax.tree_util.Partial(interpolate_cubic, bspline_coefficients(grid.values), grid.box)
