"""Sets of 2D Gaussians: a NumPy form for the host and a structure-of-arrays Warp batch for kernels.

A batch holds B independent problems (one Gaussian set each) of N slots. A slot is *active* or free;
a free slot has amplitude 0 and is skipped by every kernel. A single set is a batch of one.

Units (docs/method.md, Units and conventions, Building blocks): ``mean`` and ``sigma`` in image heights (x right, y
down, pixel centre (col, row) at ((col + 0.5) / H, (row + 0.5) / H)); ``theta`` in radians from +x towards +y;
``amplitude`` a with peak value a^2 (linear radiance); ``weight`` multiplies the Gaussian's
contribution (1 when fitting, the barycentric weight when interpolating).
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
import warp as wp

from .errors import InputError

__all__ = ["GaussianArrays", "GaussianBatch", "GaussianParams"]

_PARAMETER_SHAPES = {"amplitude": (), "mean": (2,), "sigma": (2,), "theta": (), "weight": ()}


@wp.struct
class GaussianArrays:
    """The arrays of a ``GaussianBatch`` as one kernel argument (also used for their gradients)."""

    amplitude: wp.array2d(dtype=float)
    mean: wp.array2d(dtype=wp.vec2)
    sigma: wp.array2d(dtype=wp.vec2)
    theta: wp.array2d(dtype=float)
    weight: wp.array2d(dtype=float)
    active: wp.array2d(dtype=wp.int32)


class _SlotShape:
    """(problems, slots) read off the ``active`` mask, shared by the host and device forms."""

    active: np.ndarray | wp.array

    @property
    def shape(self) -> tuple[int, int]:
        """(problems, slots)."""
        return tuple(self.active.shape)

    @property
    def problem_count(self) -> int:
        return self.active.shape[0]

    @property
    def capacity(self) -> int:
        return self.active.shape[1]


@dataclass
class GaussianParams(_SlotShape):
    """Host (NumPy, float64) copy of B sets of N Gaussian slots.

    Attributes:
        amplitude: (B, N); mean: (B, N, 2); sigma: (B, N, 2); theta: (B, N); weight: (B, N);
        active: (B, N) bool. Free slots hold zeros (weight 1).

    Values must be finite, except in a copy taken from a device batch (``GaussianBatch.numpy``),
    which shows a diverged slot as it is so that it can be found (``finite``) and removed.
    """

    amplitude: np.ndarray
    mean: np.ndarray
    sigma: np.ndarray
    theta: np.ndarray
    weight: np.ndarray
    active: np.ndarray

    def __post_init__(self):
        self._validate(require_finite=True)

    def _validate(self, *, require_finite: bool) -> None:
        self.active = np.asarray(self.active, dtype=bool)
        if self.active.ndim != 2:
            raise InputError(f"active must have shape (problems, slots), got {self.active.shape}")
        shape = self.active.shape
        for name, tail in _PARAMETER_SHAPES.items():
            value = np.asarray(getattr(self, name), dtype=np.float64)
            if value.shape != shape + tail:
                raise InputError(f"{name} must have shape {shape + tail} to match active, got {value.shape}")
            if require_finite and not np.all(np.isfinite(value)):
                raise InputError(f"{name} has non-finite values; every Gaussian parameter must be finite")
            setattr(self, name, value)

    @property
    def counts(self) -> np.ndarray:
        """Active Gaussians per problem, (B,) int."""
        return self.active.sum(axis=1)

    @property
    def finite(self) -> np.ndarray:
        """(B, N) bool: every parameter of the slot is finite."""
        finite = np.isfinite(self.amplitude) & np.isfinite(self.theta) & np.isfinite(self.weight)
        return finite & np.isfinite(self.mean).all(axis=-1) & np.isfinite(self.sigma).all(axis=-1)

    @classmethod
    def empty(cls, problem_count: int, capacity: int) -> GaussianParams:
        """B sets of N free slots."""
        if problem_count < 1 or capacity < 1:
            raise InputError(f"a batch needs at least one problem and one slot, got {problem_count} x {capacity}")
        shape = (int(problem_count), int(capacity))
        return cls(
            amplitude=np.zeros(shape),
            mean=np.zeros(shape + (2,)),
            sigma=np.zeros(shape + (2,)),
            theta=np.zeros(shape),
            weight=np.ones(shape),
            active=np.zeros(shape, dtype=bool),
        )

    @classmethod
    def from_sets(cls, sets: list[dict], capacity: int | None = None) -> GaussianParams:
        """Pack sets given as dicts of per-Gaussian arrays (amplitude (k,), mean (k, 2), sigma (k, 2),
        theta (k,), optional weight (k,)) into slots 0..k-1 of each problem."""
        sizes = [len(np.atleast_1d(s["amplitude"])) for s in sets]
        capacity = max(max(sizes, default=0), 1) if capacity is None else int(capacity)
        if max(sizes, default=0) > capacity:
            raise InputError(f"a set has {max(sizes)} Gaussians but the capacity is {capacity} slots")
        params = cls.empty(len(sets), capacity)
        for b, (gaussian_set, k) in enumerate(zip(sets, sizes, strict=True)):
            params.amplitude[b, :k] = np.reshape(gaussian_set["amplitude"], (k,))
            params.mean[b, :k] = np.reshape(gaussian_set["mean"], (k, 2))
            params.sigma[b, :k] = np.reshape(gaussian_set["sigma"], (k, 2))
            params.theta[b, :k] = np.reshape(gaussian_set["theta"], (k,))
            params.weight[b, :k] = np.reshape(gaussian_set.get("weight", np.ones(k)), (k,))
            params.active[b, :k] = True
        params.__post_init__()
        return params

    def copy(self) -> GaussianParams:
        return GaussianParams(**{f.name: getattr(self, f.name).copy() for f in fields(self)})

    def take(self, rows) -> GaussianParams:
        """The problems ``rows`` (an index array, repeats allowed), e.g. every directed edge's source set."""
        return GaussianParams(**{f.name: getattr(self, f.name)[rows] for f in fields(self)})

    def where(self, slots: np.ndarray, other: GaussianParams) -> GaussianParams:
        """A new batch of this shape: the (B, N) ``slots`` from this one, the others from ``other``."""
        slots = np.asarray(slots, dtype=bool)
        return GaussianParams(**{f.name: np.where(slots.reshape(slots.shape + (1,) * (getattr(self, f.name).ndim - 2)),
                                                  getattr(self, f.name), getattr(other, f.name))
                                 for f in fields(self)})

    @classmethod
    def concatenate(cls, parts: list[GaussianParams], *, axis: int = 0) -> GaussianParams:
        """Join batches along the problems (axis 0) or, for equal problem counts, along the slots (axis 1)."""
        if len(parts) == 1:
            return parts[0]
        return cls(**{f.name: np.concatenate([getattr(p, f.name) for p in parts], axis=axis) for f in fields(cls)})


class GaussianBatch(_SlotShape):
    """B Gaussian sets of N slots as Warp arrays (structure of arrays), the input of every kernel.

    Arrays (all shape (B, N)): ``amplitude`` float32, ``mean`` vec2, ``sigma`` vec2, ``theta``
    float32, ``weight`` float32, ``active`` int32 (1 = in use). With ``requires_grad`` the five
    parameter arrays carry ``.grad`` arrays of the same shape, which the rasterizer and the losses
    fill through ``wp.Tape``. ``arrays`` and ``grad_arrays`` bundle them as one ``GaussianArrays``
    kernel argument.
    """

    def __init__(self, problem_count: int, capacity: int, *, device=None, requires_grad: bool = True):
        if problem_count < 1 or capacity < 1:
            raise InputError(f"a batch needs at least one problem and one slot, got {problem_count} x {capacity}")
        self.device = wp.get_device(device)
        self.requires_grad = bool(requires_grad)
        shape = (int(problem_count), int(capacity))
        kwargs = {"shape": shape, "device": self.device, "requires_grad": self.requires_grad}
        self.amplitude = wp.zeros(dtype=wp.float32, **kwargs)
        self.mean = wp.zeros(dtype=wp.vec2, **kwargs)
        self.sigma = wp.zeros(dtype=wp.vec2, **kwargs)
        self.theta = wp.zeros(dtype=wp.float32, **kwargs)
        self.weight = wp.ones(dtype=wp.float32, **kwargs)
        self.active = wp.zeros(shape, dtype=wp.int32, device=self.device)
        # bumped whenever a slot gets new contents from the host, so optimisers restart its state
        self.generation = wp.zeros(shape, dtype=wp.int32, device=self.device)
        self.arrays = self._struct(self.parameters())
        self.grad_arrays = self._struct([a.grad for a in self.parameters()]) if self.requires_grad else None

    def _struct(self, parameters: list[wp.array]) -> GaussianArrays:
        arrays = GaussianArrays()
        arrays.amplitude, arrays.mean, arrays.sigma, arrays.theta, arrays.weight = parameters
        arrays.active = self.active
        return arrays

    def parameters(self) -> list[wp.array]:
        """The differentiable arrays: amplitude, mean, sigma, theta, weight."""
        return [self.amplitude, self.mean, self.sigma, self.theta, self.weight]

    def counts(self) -> np.ndarray:
        """Active Gaussians per problem, (B,) int (copies the mask to the host)."""
        return self.active.numpy().sum(axis=1)

    # --- host conversion ---------------------------------------------------------------------------

    @classmethod
    def from_numpy(cls, params: GaussianParams, *, device=None, requires_grad: bool = True) -> GaussianBatch:
        """A device batch holding ``params`` (float64 values are rounded to float32)."""
        batch = cls(params.problem_count, params.capacity, device=device, requires_grad=requires_grad)
        batch.assign(params)
        return batch

    def numpy(self) -> GaussianParams:
        """Copy to the host as float64 ``GaussianParams`` (non-finite values of diverged slots kept)."""
        params = GaussianParams.__new__(GaussianParams)
        params.amplitude = self.amplitude.numpy().astype(np.float64)
        params.mean = self.mean.numpy().astype(np.float64)
        params.sigma = self.sigma.numpy().astype(np.float64)
        params.theta = self.theta.numpy().astype(np.float64)
        params.weight = self.weight.numpy().astype(np.float64)
        params.active = self.active.numpy() != 0
        params._validate(require_finite=False)
        return params

    def gradients(self) -> dict[str, np.ndarray]:
        """The parameter gradients as float64 NumPy arrays, keyed like the parameters."""
        if not self.requires_grad:
            raise InputError("this batch was made with requires_grad=False, so it has no gradients")
        return {name: getattr(self, name).grad.numpy().astype(np.float64) for name in _PARAMETER_SHAPES}

    def assign(self, params: GaussianParams) -> None:
        """Overwrite every slot with ``params`` (same problems and capacity); free slots are zeroed."""
        if (params.problem_count, params.capacity) != self.shape:
            raise InputError(
                f"cannot assign {params.problem_count} x {params.capacity} Gaussians to a batch of "
                f"{self.problem_count} problems x {self.capacity} slots"
            )
        active = params.active
        pairs = active[..., None]
        self.amplitude.assign(np.where(active, params.amplitude, 0.0).astype(np.float32))
        self.mean.assign(np.where(pairs, params.mean, 0.0).astype(np.float32))
        self.sigma.assign(np.where(pairs, params.sigma, 0.0).astype(np.float32))
        self.theta.assign(np.where(active, params.theta, 0.0).astype(np.float32))
        self.weight.assign(np.where(active, params.weight, 1.0).astype(np.float32))
        self.active.assign(active.astype(np.int32))
        self._renew(np.ones(self.shape, dtype=bool))

    def copy_from(self, other: GaussianBatch) -> None:
        """Device-side copy of another batch of the same shape (no host round trip)."""
        if other.shape != self.shape:
            raise InputError(f"cannot copy a {other.shape} batch into a {self.shape} batch")
        for name in ("amplitude", "mean", "sigma", "theta", "weight", "active"):
            wp.copy(getattr(self, name), getattr(other, name))
        self._renew(np.ones(self.shape, dtype=bool))

    def clone(self, *, requires_grad: bool | None = None) -> GaussianBatch:
        """A new batch on the same device with the same contents."""
        copy = GaussianBatch(*self.shape, device=self.device,
                             requires_grad=self.requires_grad if requires_grad is None else requires_grad)
        copy.copy_from(self)
        return copy

    # --- slot management ---------------------------------------------------------------------------

    def add(self, problems, amplitude, mean, sigma, theta, weight=None) -> np.ndarray:
        """Put new Gaussians into the lowest free slots of their problems; returns their slot indices.

        ``problems`` (k,) gives each new Gaussian's problem; the other arguments are (k,) or (k, 2)
        in the units of the module docstring. Raises ``InputError`` (and changes nothing) when a
        problem would exceed its capacity.
        """
        problems = np.asarray(problems, dtype=np.int64).reshape(-1)
        count = problems.size
        new = GaussianParams(
            amplitude=np.reshape(amplitude, (1, count)),
            mean=np.reshape(mean, (1, count, 2)),
            sigma=np.reshape(sigma, (1, count, 2)),
            theta=np.reshape(theta, (1, count)),
            weight=np.reshape(np.ones(count) if weight is None else weight, (1, count)),
            active=np.ones((1, count), dtype=bool),
        )
        if count and (problems.min() < 0 or problems.max() >= self.problem_count):
            raise InputError(f"problem index out of range 0..{self.problem_count - 1}")
        params = self.numpy()
        # rank of each new Gaussian among those of its problem, then the rank-th free slot there
        order = np.argsort(problems, kind="stable")
        sorted_problems = problems[order]
        first = np.searchsorted(sorted_problems, sorted_problems, side="left")
        rank = np.empty(count, dtype=np.int64)
        rank[order] = np.arange(count) - first
        free_count = (~params.active).sum(axis=1)
        needed = np.bincount(problems, minlength=self.problem_count)
        full = np.flatnonzero(needed > free_count)
        if full.size:
            b = int(full[0])
            raise InputError(
                f"problem {b} has {free_count[b]} free slots of {self.capacity} but {needed[b]} Gaussians were "
                f"added; raise the capacity or remove Gaussians first"
            )
        # a stable sort of the active flags lists each row's free slots first, in ascending order
        free_slots = np.argsort(params.active, axis=1, kind="stable")
        slots = free_slots[problems, rank]
        for name in _PARAMETER_SHAPES:
            getattr(params, name)[problems, slots] = getattr(new, name)[0]
        params.active[problems, slots] = True
        generation = self.generation.numpy().copy()  # a CPU array's numpy() is a view
        self.assign(params)
        generation[problems, slots] += 1  # only the new slots restart their optimiser state
        self.generation.assign(generation)
        return slots

    def remove(self, mask) -> int:
        """Free the slots where ``mask`` (B, N) is true; returns how many active Gaussians were removed."""
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != self.shape:
            raise InputError(f"remove mask must have shape {self.shape}, got {mask.shape}")
        params = self.numpy()
        removed = int(np.count_nonzero(mask & params.active))
        params.active &= ~mask
        generation = self.generation.numpy().copy()  # a CPU array's numpy() is a view
        self.assign(params)
        self.generation.assign(generation)
        return removed

    def _renew(self, mask: np.ndarray) -> None:
        generation = self.generation.numpy().copy()  # a CPU array's numpy() is a view
        generation[mask] += 1
        self.generation.assign(generation)
