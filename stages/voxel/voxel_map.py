"""Sparse log-odds voxel map on integer keys (the OctoMap occupancy update at the leaf level).

OctoMap (Hornung et al. 2013) keeps per voxel the log-odds ``L = log(p / (1 - p))``; a hit adds
``logit(p_hit)``, a miss adds ``logit(p_miss)`` and the result is clamped to
``[logit(clamp_min), logit(clamp_max)]`` after every update. A voxel is occupied when
``L > logit(occupancy_threshold)``. Within one scan every voxel is updated at most once, and a voxel that
is both "free" and "hit" in the same scan counts as a hit (``OccupancyOcTreeBase::computeUpdate``).

Storage: voxels are grouped into 16^3 blocks (a block-sparse hash, as in voxblox/OpenVDB). Block
coordinates are packed into one int64 and kept in a sorted key array with a slot index; each block slot
holds 4096 float32 log-odds, NaN meaning "unknown". A scan update is vectorised: the scan's keys are
rasterised into a dense boolean window aligned to block boundaries, the touched blocks are gathered,
updated and scattered back. No sort over the scan's voxels is needed.

Keys follow OctoMap's discretisation: ``key = floor(coordinate * (1 / resolution))`` (OctoMap adds a
constant offset of 2^15 that we leave out); a voxel's centre is ``(key + 0.5) * resolution``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

BLOCK_BITS = 4
BLOCK = 1 << BLOCK_BITS  # voxels per block edge
BLOCK_VOXELS = BLOCK**3
_PACK_BITS = 21
_PACK_OFFSET = 1 << (_PACK_BITS - 1)
#: largest dense window (cells) rasterised at once; bigger scans are split into tiles
MAX_WINDOW_CELLS = 1 << 25

IntArray = npt.NDArray[np.int64]
FloatArray = npt.NDArray[np.float64]


def logit(p: float) -> float:
    """Log-odds of a probability (OctoMap ``logodds``)."""
    return float(np.log(p / (1.0 - p)))


def coord_to_key(points: npt.ArrayLike, resolution: float) -> IntArray:
    """Integer voxel keys of points, ``floor(x * (1/res))`` as OctoMap's ``coordToKey`` (without its offset)."""
    pts = np.asarray(points, dtype=np.float64)
    return np.floor(pts * (1.0 / resolution)).astype(np.int64)


def key_to_coord(keys: npt.ArrayLike, resolution: float) -> FloatArray:
    """Voxel centres of integer keys."""
    return (np.asarray(keys, dtype=np.float64) + 0.5) * resolution


def pack_keys(keys: npt.ArrayLike) -> IntArray:
    """Pack (N, 3) integer keys (each within +-2^20) into one sortable int64 (x major, z minor)."""
    k = np.asarray(keys, dtype=np.int64) + _PACK_OFFSET
    return (k[:, 0] << (2 * _PACK_BITS)) | (k[:, 1] << _PACK_BITS) | k[:, 2]


def unpack_keys(packed: npt.ArrayLike) -> IntArray:
    """Inverse of :func:`pack_keys`."""
    p = np.asarray(packed, dtype=np.int64)
    mask = (1 << _PACK_BITS) - 1
    out = np.stack([(p >> (2 * _PACK_BITS)) & mask, (p >> _PACK_BITS) & mask, p & mask], axis=1)
    return out - _PACK_OFFSET


@dataclass(frozen=True)
class SensorModel:
    """OctoMap occupancy parameters (probabilities; defaults are OctoMap's and the ColoRadar fork's)."""

    prob_hit: float = 0.7
    prob_miss: float = 0.4
    clamp_min: float = 0.12
    clamp_max: float = 0.97
    occupancy_threshold: float = 0.5

    def __post_init__(self) -> None:
        for name in ("prob_hit", "prob_miss", "clamp_min", "clamp_max", "occupancy_threshold"):
            v = getattr(self, name)
            if not 0.0 < v < 1.0:
                raise ValueError(f"{name} must lie strictly between 0 and 1, got {v}")
        if not self.clamp_min < self.clamp_max:
            raise ValueError(f"clamp_min ({self.clamp_min}) must be below clamp_max ({self.clamp_max})")

    @property
    def hit(self) -> np.float32:
        return np.float32(logit(self.prob_hit))

    @property
    def miss(self) -> np.float32:
        return np.float32(logit(self.prob_miss))

    @property
    def lo(self) -> np.float32:
        return np.float32(logit(self.clamp_min))

    @property
    def hi(self) -> np.float32:
        return np.float32(logit(self.clamp_max))

    @property
    def threshold(self) -> np.float32:
        return np.float32(logit(self.occupancy_threshold))


class VoxelMap:
    """Block-sparse log-odds map; :meth:`integrate` applies one scan's free and hit voxels."""

    def __init__(self, resolution: float, model: SensorModel | None = None) -> None:
        if resolution <= 0:
            raise ValueError(f"resolution must be positive, got {resolution}")
        self.resolution = float(resolution)
        self.model = model or SensorModel()
        self._sorted_keys = np.zeros(0, np.int64)  # packed block keys, sorted
        self._sorted_slots = np.zeros(0, np.int64)  # slot of each sorted key
        self._values = np.full((0, BLOCK_VOXELS), np.nan, np.float32)
        self._n_blocks = 0
        self.n_updates = 0  # voxel updates applied (hits + misses)

    # -- block bookkeeping --------------------------------------------------------------------------
    @property
    def n_blocks(self) -> int:
        return self._n_blocks

    def _slots(self, block_keys: IntArray) -> IntArray:
        """Slots of packed block keys, creating the missing blocks (filled with NaN = unknown)."""
        if len(self._sorted_keys):
            pos = np.minimum(np.searchsorted(self._sorted_keys, block_keys), len(self._sorted_keys) - 1)
            found = self._sorted_keys[pos] == block_keys
        else:
            pos = np.zeros(len(block_keys), np.int64)
            found = np.zeros(len(block_keys), bool)
        slots = np.empty(len(block_keys), np.int64)
        if np.any(found):
            slots[found] = self._sorted_slots[pos[found]]
        new = ~found
        n_new = int(new.sum())
        if n_new:
            first = self._n_blocks
            need = first + n_new
            if need > len(self._values):
                grown = np.full((max(need, 2 * len(self._values), 64), BLOCK_VOXELS), np.nan, np.float32)
                grown[: self._n_blocks] = self._values[: self._n_blocks]
                self._values = grown
            new_slots = np.arange(first, need, dtype=np.int64)
            slots[new] = new_slots
            keys = np.concatenate([self._sorted_keys, block_keys[new]])
            sl = np.concatenate([self._sorted_slots, new_slots])
            order = np.argsort(keys, kind="stable")
            self._sorted_keys, self._sorted_slots = keys[order], sl[order]
            self._n_blocks = need
        return slots

    # -- updates ------------------------------------------------------------------------------------
    def integrate(self, free_keys: npt.ArrayLike, hit_keys: npt.ArrayLike, hits_need_free: bool = False) -> None:
        """Apply one scan: each distinct voxel once; hits win over misses.

        ``free_keys``/``hit_keys`` are (N, 3) integer voxel keys, duplicates allowed. With
        ``hits_need_free`` a hit counts only where the voxel is also in the free set (the radar sensor
        model: a return is a hit only inside the field-of-view fan), otherwise it is dropped.
        """
        free = np.ascontiguousarray(np.asarray(free_keys).reshape(-1, 3).T)
        hit = np.ascontiguousarray(np.asarray(hit_keys).reshape(-1, 3).T)
        if not np.issubdtype(free.dtype, np.integer) or not np.issubdtype(hit.dtype, np.integer):
            raise TypeError("voxel keys must be integer arrays")
        if hits_need_free and free.shape[1] == 0:
            return
        parts = [free] if hits_need_free or hit.shape[1] == 0 else [free, hit]
        if sum(p.shape[1] for p in parts) == 0:
            return
        lo = np.min([p.min(axis=1) for p in parts if p.shape[1]], axis=0).astype(np.int64) >> BLOCK_BITS
        hi = (np.max([p.max(axis=1) for p in parts if p.shape[1]], axis=0).astype(np.int64) >> BLOCK_BITS) + 1
        if int(np.prod(hi - lo)) * BLOCK_VOXELS > MAX_WINDOW_CELLS:
            self._integrate_tiled(free, hit, hits_need_free)
            return
        self._integrate_window(free, hit, lo, hi - lo, hits_need_free)

    def _integrate_tiled(self, free: IntArray, hit: IntArray, hits_need_free: bool) -> None:
        """Split a scan spanning a huge window into tiles of 16^3 blocks (same result, more passes)."""
        tile_bits = 4 + BLOCK_BITS
        ft, ht = free >> tile_bits, hit >> tile_bits
        tiles = np.unique(np.concatenate([ft, ht], axis=1), axis=1)
        shape = np.full(3, 1 << (tile_bits - BLOCK_BITS), np.int64)
        for t in tiles.T:
            fm = np.all(ft == t[:, None], axis=0)
            hm = np.all(ht == t[:, None], axis=0)
            self._integrate_window(free[:, fm], hit[:, hm], t << (tile_bits - BLOCK_BITS), shape, hits_need_free)

    @staticmethod
    def _raster(keys: IntArray, lo_block: IntArray, nb: IntArray, check: bool) -> npt.NDArray[np.bool_]:
        """Dense C-order window (x, y, z) marking (3, N) keys, re-laid out block-major as (blocks, 4096)."""
        sx, sy, sz = (int(v) << BLOCK_BITS for v in nb)
        origin = lo_block << BLOCK_BITS
        if check:  # keys may lie outside the window (or beyond int32): test in int64 first
            rel64 = keys.astype(np.int64, copy=False) - origin[:, None]
            inside = np.all((rel64 >= 0) & (rel64 < np.array([sx, sy, sz])[:, None]), axis=0)
            rel = [rel64[i, inside].astype(np.int32) for i in range(3)]
        else:
            k32 = keys.astype(np.int32, copy=False)
            rel = [k32[i] - np.int32(origin[i]) for i in range(3)]
        bm = np.zeros(sx * sy * sz, bool)
        idx = rel[0] * np.int32(sy)
        idx += rel[1]
        idx *= np.int32(sz)
        idx += rel[2]
        bm[idx] = True
        bx, by, bz = (int(v) for v in nb)
        six = bm.reshape(bx, BLOCK, by, BLOCK, bz, BLOCK).transpose(0, 2, 4, 1, 3, 5)
        return np.ascontiguousarray(six).reshape(bx * by * bz, BLOCK_VOXELS)

    def _integrate_window(
        self, free: IntArray, hit: IntArray, lo_block: IntArray, nb: IntArray, hits_need_free: bool
    ) -> None:
        n_blocks = int(np.prod(nb))
        empty = np.zeros((n_blocks, BLOCK_VOXELS), bool)
        free_bm = self._raster(free, lo_block, nb, check=False) if free.shape[1] else empty
        hit_bm = self._raster(hit, lo_block, nb, check=True) if hit.shape[1] else empty.copy()
        if hits_need_free:
            hit_bm &= free_bm
        free_bm &= ~hit_bm
        active = np.flatnonzero(free_bm.any(axis=1) | hit_bm.any(axis=1))
        if len(active) == 0:
            return
        fmask, hmask = free_bm[active], hit_bm[active]
        bidx = np.stack(np.unravel_index(active, tuple(int(v) for v in nb)), axis=1) + lo_block
        slots = self._slots(pack_keys(bidx))
        vals = self._values[slots]
        m = self.model
        base = np.where(np.isnan(vals), np.float32(0.0), vals)
        upd = np.where(hmask, m.hit, np.where(fmask, m.miss, np.float32(0.0)))
        new = np.clip(base + upd, m.lo, m.hi)
        touched = fmask | hmask
        self._values[slots] = np.where(touched, new, vals)
        self.n_updates += int(np.count_nonzero(touched))

    # -- read-out -----------------------------------------------------------------------------------
    def voxels(self, occupied_only: bool = True) -> tuple[IntArray, npt.NDArray[np.float32]]:
        """Keys (N, 3) and log-odds of known voxels (occupied only by default), grouped by block."""
        if self._n_blocks == 0:
            return np.zeros((0, 3), np.int64), np.zeros(0, np.float32)
        vals = self._values[self._sorted_slots]
        mask = vals > self.model.threshold if occupied_only else ~np.isnan(vals)
        bi, vi = np.nonzero(mask)
        bkeys = unpack_keys(self._sorted_keys[bi]) << BLOCK_BITS
        local = np.stack([vi >> (2 * BLOCK_BITS), (vi >> BLOCK_BITS) & (BLOCK - 1), vi & (BLOCK - 1)], axis=1)
        return bkeys + local, vals[bi, vi]

    def centres(self, occupied_only: bool = True) -> tuple[FloatArray, npt.NDArray[np.float32]]:
        """Voxel centres (N, 3) and log-odds (occupied only by default)."""
        keys, lo = self.voxels(occupied_only)
        return key_to_coord(keys, self.resolution), lo

    def counts(self) -> dict[str, int]:
        """Numbers of known, occupied and free voxels."""
        if self._n_blocks == 0:
            return {"known": 0, "occupied": 0, "free": 0}
        vals = self._values[: self._n_blocks]
        known = int((~np.isnan(vals)).sum())
        occ = int((vals > self.model.threshold).sum())
        return {"known": known, "occupied": occ, "free": known - occ}
