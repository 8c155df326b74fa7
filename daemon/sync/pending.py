"""The profiles a :class:`~.pairing.Pairer` holds until their states arrive, kept as blocks.

Profiles stay in the :class:`~wristscan.drivers.records.ProfileBlock` they arrived in; what the
pairer needs per profile lives in one table (block, row, sensor time, clock epoch, receipt,
sensor id, frame counter; one column per profile, in arrival order). Records from
:meth:`Pairer.add_profile` are staged and stacked into blocks (runs of equal length and equal
intensity presence) when the pairer next looks at them. Released profiles become
:class:`~.batch.Segment` s: runs of consecutive rows of a block, as views (no copy); profiles
released in too many runs (heavily reordered, interleaved sensors) are copied once instead,
block by block (:meth:`PendingProfiles.gather`). A lateral grid shared by every released
profile stays shared.

Memory is bounded by the pending profiles: blocks no pending profile refers to are dropped, and
when the blocks kept hold more than twice the pending rows (+ 1024), the mostly released ones
are copied down to their waiting rows.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from wristscan.daemon.sync.batch import Segment
from wristscan.drivers.records import Profile, ProfileBlock

__all__ = ["Gathered", "PendingProfiles"]

IntArray = NDArray[np.int64]
FloatArray = NDArray[np.float64]

# Staged records are stacked into blocks once this many wait (bounded memory without a poll).
_STAGE_LIMIT = 4096
# Released profiles in more runs than this (heavily reordered) are copied, not viewed.
_MAX_SEGMENTS = 32
# Blocks may hold this many rows beyond twice the pending ones before they are copied down.
_SLACK_ROWS = 1024


@dataclass
class Gathered:
    """The points and identities of released profiles, in the order asked for: runs of
    consecutive rows of a block as segments (views), or, for profiles too interleaved for
    that, flat copies (``y`` None when ``y_grid`` is shared)."""

    sensor_id: IntArray
    frame_counter: IntArray
    offsets: IntArray
    y_grid: FloatArray | None
    points_per_profile: int | None = None
    segments: list[Segment] | None = None
    y: FloatArray | None = None
    z: FloatArray | None = None
    valid: NDArray[np.bool_] | None = None
    intensity: NDArray[np.uint8] | None = None


def _stack(run: list[Profile]) -> ProfileBlock:
    """One block of records of equal length (a grid shared by all of them stays shared)."""
    p = len(run)
    y0 = run[0].y
    has_i = run[0].intensity is not None
    return ProfileBlock(
        sensor_id=np.fromiter((r.sensor_id for r in run), np.int64, p),
        frame_counter=np.fromiter((r.frame_counter for r in run), np.int64, p),
        sensor_time_ns=np.fromiter((r.sensor_time_ns for r in run), np.int64, p),
        host_time_ns=np.fromiter((r.host_time_ns for r in run), np.int64, p),
        y=y0 if all(r.y is y0 for r in run) else np.stack([r.y for r in run]),
        z=np.stack([r.z for r in run]),
        valid=np.stack([r.valid for r in run]),
        intensity=np.stack([r.intensity for r in run]) if has_i else None,  # type: ignore[misc]
    )


def _runs(records: list[Profile]) -> list[list[Profile]]:
    """Consecutive records of equal length and equal intensity presence."""
    out: list[list[Profile]] = []
    key: tuple[int, bool] | None = None
    for r in records:
        k = (r.y.shape[0], r.intensity is not None)
        if k != key:
            out.append([])
            key = k
        out[-1].append(r)
    return out


class PendingProfiles:
    """Pending profiles in arrival order: their blocks and per-profile arrays."""

    def __init__(self) -> None:
        self.clear()

    def clear(self) -> None:
        """Forget every pending profile."""
        self.blocks: list[ProfileBlock] = []
        # One row per column, one column per pending profile: block index, row in it, sensor
        # time (or count), epoch, receipt, sensor id, frame counter (one array: one
        # concatenation and one selection per poll for all of them).
        self.table = np.zeros((7, 0), dtype=np.int64)
        self._chunks: list[IntArray] = []
        self._staged: list[Profile] = []
        self._staged_xe: list[tuple[int, int]] = []
        self._n = 0
        self._whole = False  # the table is one block's rows 0, 1, ... in order
        self._chunk_whole = False  # so is the last chunk queued
        self._skip = 0  # oldest profiles dropped but not yet removed from the table
        self._keys: set[tuple[int, int]] | None = set()
        """(sensor id, epoch) pairs of the pending profiles, a superset (None: not known)."""

    def __len__(self) -> int:
        return self._n - self._skip

    @property
    def block(self) -> IntArray:
        return self.table[0]

    @property
    def row(self) -> IntArray:
        return self.table[1]

    @property
    def x(self) -> IntArray:
        return self.table[2]

    @property
    def epoch(self) -> IntArray:
        return self.table[3]

    @property
    def host(self) -> IntArray:
        return self.table[4]

    @property
    def sid(self) -> IntArray:
        return self.table[5]

    @property
    def fc(self) -> IntArray:
        return self.table[6]

    # ------------------------------------------------------------------ input

    def add_block(
        self,
        block: ProfileBlock,
        rows: IntArray | None,
        x: IntArray,
        epoch: IntArray,
        key: tuple[int, int] | None = None,
    ) -> None:
        """Queue ``rows`` of ``block`` (all when None) with their sensor times and epochs;
        ``key``: the (sensor id, epoch) of every row, if one. The block's arrays are kept, not
        copied: the caller must not reuse them."""
        self._stage_out()
        if rows is None or rows.shape[0]:
            self.note_key(key)
            self._append(block, rows, x, epoch)

    def _append(
        self, block: ProfileBlock, rows: IntArray | None, x: IntArray, epoch: IntArray
    ) -> None:
        n = block.n_profiles if rows is None else int(rows.shape[0])
        t = np.empty((7, n), dtype=np.int64)
        t[0] = len(self.blocks)
        if rows is None:
            t[1] = np.arange(n)
            t[2:] = (x, epoch, block.host_time_ns, block.sensor_id, block.frame_counter)
        else:
            t[1] = rows
            t[2:] = (
                x,
                epoch,
                block.host_time_ns[rows],
                block.sensor_id[rows],
                block.frame_counter[rows],
            )
        self.blocks.append(block)
        self._chunks.append(t)
        self._chunk_whole = rows is None
        self._n += n

    def add_record(self, profile: Profile, x: int, epoch: int) -> None:
        """Queue one record (stacked with its neighbours when next needed)."""
        self._staged.append(profile)
        self._staged_xe.append((x, epoch))
        self.note_key((profile.sensor_id, epoch))
        self._n += 1
        if len(self._staged) >= _STAGE_LIMIT:
            self._stage_out()

    def note_key(self, key: tuple[int, int] | None) -> None:
        """Profiles of (sensor id, epoch) ``key`` are pending (None: of several)."""
        if key is None:
            self._keys = None
        elif self._keys is not None:
            self._keys.add(key)

    def single_key(self) -> tuple[int, int] | None:
        """The (sensor id, epoch) of every pending profile when it is known to be one."""
        keys = self._keys
        return next(iter(keys)) if keys is not None and len(keys) == 1 else None

    def set_keys(self, keys: set[tuple[int, int]]) -> None:
        """The (sensor id, epoch) pairs found in the consolidated table."""
        self._keys = keys

    def drop_oldest(self, k: int) -> None:
        """Forget the ``k`` oldest pending profiles (overflow)."""
        self._skip += k
        if self._skip >= _STAGE_LIMIT:
            self.consolidate()

    def _stage_out(self) -> None:
        """Stack the staged records into blocks."""
        if not self._staged:
            return
        staged, xe = self._staged, np.array(self._staged_xe, dtype=np.int64).reshape(-1, 2)
        self._staged, self._staged_xe = [], []
        self._n -= len(staged)
        a = 0
        for run in _runs(staged):
            b = a + len(run)
            self._append(_stack(run), None, xe[a:b, 0], xe[a:b, 1])
            a = b

    def consolidate(self) -> None:
        """Bring every queued profile into :attr:`table` (in arrival order)."""
        self._stage_out()
        if self._chunks:
            if self.table.shape[1] == 0 and len(self._chunks) == 1:
                self.table = self._chunks[0]  # the usual tick: nothing held over, one block
                self._whole = self._chunk_whole
            else:
                self.table = np.concatenate([self.table, *self._chunks], axis=1)
                self._whole = False
            self._chunks = []
        if self._skip:
            skip, self._skip = self._skip, 0
            self.keep(np.arange(skip, self._n, dtype=np.int64))

    # ------------------------------------------------------------------ release

    def keep(self, idx: IntArray) -> None:
        """Keep only the pending profiles ``idx`` (increasing indices into the table, after
        :meth:`consolidate`); the others are gone."""
        assert not (self._chunks or self._staged or self._skip), "consolidate() first"
        self.table = self.table[:, idx]
        self._n = int(idx.shape[0])
        self._whole = False
        self._prune()

    def _prune(self) -> None:
        """Drop the blocks no pending profile refers to. Block indices are non-decreasing in
        arrival order, so the blocks in use are those from the first profile's to the last's;
        when they hold more than twice the pending rows (+ slack), the mostly released ones are
        copied down to their waiting rows (bounded memory)."""
        if self._n == 0:
            self.blocks = []
            self._keys = set()
            return
        ids = self.table[0]
        lo, hi = int(ids[0]), int(ids[-1])
        if lo or hi + 1 < len(self.blocks):
            self.blocks = self.blocks[lo : hi + 1]
            if lo:
                ids -= lo
        if sum(b.n_profiles for b in self.blocks) <= 2 * self._n + _SLACK_ROWS:
            return
        used = np.bincount(ids, minlength=len(self.blocks))
        starts = np.concatenate([[0], np.cumsum(used)])
        new_index = np.cumsum(used > 0) - 1
        kept: list[ProfileBlock] = []
        for b in np.flatnonzero(used).tolist():
            blk = self.blocks[b]
            if 2 * int(used[b]) < blk.n_profiles:
                m = slice(int(starts[b]), int(starts[b + 1]))
                blk = blk.take(self.table[1, m])
                self.table[1, m] = np.arange(int(used[b]))
            kept.append(blk)
        self.blocks = kept
        self.table[0] = new_index[ids]

    def gather(self, sel: IntArray | slice) -> Gathered:
        """The profiles ``sel`` (indices into the consolidated arrays, or a slice of them) in
        that order: runs of consecutive rows of a block as views (no copy); heavily interleaved
        ones copied once, block by block."""
        P = (
            int(sel.shape[0])
            if isinstance(sel, np.ndarray)
            else len(range(*sel.indices(len(self))))
        )
        if len(self.blocks) == 1:
            one = self._gather_run(sel, P)
            if one is not None:
                return one
        bid, row = self.block[sel], self.row[sel]
        nb = np.fromiter((b.n_points for b in self.blocks), np.int64, len(self.blocks))
        offsets = np.zeros(P + 1, dtype=np.int64)
        np.cumsum(nb[bid], out=offsets[1:])
        out = Gathered(self.sid[sel], self.fc[sel], offsets, None)
        sizes = {int(b.n_points) for b in self.blocks}
        out.points_per_profile = sizes.pop() if len(sizes) == 1 else None
        runs = np.flatnonzero((bid[1:] != bid[:-1]) | (row[1:] != row[:-1] + 1)) + 1
        if runs.shape[0] < _MAX_SEGMENTS:
            cuts = [0, *runs.tolist(), P]
            out.segments = []
            for a, b in itertools.pairwise(cuts):
                blk = self.blocks[int(bid[a])]
                r = slice(int(row[a]), int(row[a]) + b - a)
                y = blk.y if blk.y.ndim == 1 else blk.y[r]
                inten = None if blk.intensity is None else blk.intensity[r]
                out.segments.append(_segment(a, y, blk, r, inten))
            out.y_grid = _shared_grid([self.blocks[int(bid[a])] for a in cuts[:-1]])
            return out
        groups = _groups(bid, row)
        used = [self.blocks[b] for b, _, _ in groups]
        out.y_grid = grid = _shared_grid(used)
        total = int(offsets[-1])
        out.y = None if grid is not None else np.empty(total)
        out.z = np.empty(total)
        out.valid = np.empty(total, dtype=np.bool_)
        if all(b.intensity is not None for b in used):
            out.intensity = np.empty(total, dtype=np.uint8)
        for (_, rows, pos), blk in zip(groups, used, strict=True):
            _copy_rows(out, blk, rows, pos, offsets)
        return out

    def _gather_run(self, sel: IntArray | slice, P: int) -> Gathered | None:
        """:meth:`gather` when one block is held and ``sel`` are consecutive rows of it, in
        order (the usual tick): one segment, without the run search; None otherwise."""
        run = sel.indices(self._n) if self._whole and P and isinstance(sel, slice) else None
        if run is not None and run[2] == 1:
            r0 = run[0]  # rows r0, r0 + 1, ...: the table is the block in order
        else:
            row = self.row[sel]
            r0 = int(row[0]) if P else 0
            if P == 0 or int(row[-1]) - r0 != P - 1 or not bool((np.diff(row) == 1).all()):
                return None
        blk = self.blocks[0]
        N = blk.n_points
        r = slice(r0, r0 + P)
        y = blk.y if blk.y.ndim == 1 else blk.y[r]
        inten = None if blk.intensity is None else blk.intensity[r]
        out = Gathered(
            self.sid[sel], self.fc[sel], np.arange(0, (P + 1) * N, N, dtype=np.int64), None
        )
        out.points_per_profile = N
        out.segments = [_segment(0, y, blk, r, inten)]
        out.y_grid = blk.y if blk.y.ndim == 1 else None
        return out


def _segment(
    start: int, y: FloatArray, blk: ProfileBlock, r: slice, inten: NDArray[np.uint8] | None
) -> Segment:
    """Rows ``r`` of ``blk`` as a segment: views, its points still coded when the block's are."""
    if blk.coded and blk.codes is not None:
        return Segment(start, y, None, blk.valid[r], inten, blk.codes.take(r))
    return Segment(start, y, blk.z[r], blk.valid[r], inten)


def _groups(bid: IntArray, row: IntArray) -> list[tuple[int, IntArray, slice | IntArray]]:
    """(block, its rows, their positions in the output) for each block, in block order."""
    P = bid.shape[0]
    if P and bid[0] == bid[-1] and np.all(bid == bid[0]):
        return [(int(bid[0]), row, slice(0, P))]
    order = np.argsort(bid, kind="stable")
    sb = bid[order]
    cuts = [0, *(np.flatnonzero(sb[1:] != sb[:-1]) + 1).tolist(), P]
    out: list[tuple[int, IntArray, slice | IntArray]] = []
    for a, c in itertools.pairwise(cuts):
        pos = order[a:c]
        p: slice | IntArray = pos
        if int(pos[-1]) - int(pos[0]) == c - a - 1:
            p = slice(int(pos[0]), int(pos[-1]) + 1)
        out.append((int(sb[a]), row[pos], p))
    return out


def _run_of(rows: IntArray) -> slice | None:
    """``rows`` as a slice when they are consecutive and increasing."""
    k = rows.shape[0]
    if k and int(rows[-1]) - int(rows[0]) == k - 1 and np.all(np.diff(rows) == 1):
        return slice(int(rows[0]), int(rows[-1]) + 1)
    return None


def _shared_grid(blocks: list[ProfileBlock]) -> FloatArray | None:
    """The lateral grid every block shares (the same array), else None."""
    y0 = blocks[0].y
    if y0.ndim != 1:
        return None
    for b in blocks[1:]:
        if b.y is not y0 and (b.y.ndim != 1 or not np.array_equal(b.y, y0)):
            return None
    return y0


def _copy_rows(
    out: Gathered, blk: ProfileBlock, rows: IntArray, pos: slice | IntArray, offsets: IntArray
) -> None:
    """Copy ``rows`` of ``blk`` to the output profiles ``pos``: one copy per array."""
    N = blk.n_points
    k = rows.shape[0]
    run = _run_of(rows)
    src: slice | IntArray = rows if run is None else run
    assert out.z is not None and out.valid is not None
    pairs: list[tuple[NDArray[np.generic], NDArray[np.generic]]] = [
        (out.z, blk.z),
        (out.valid, blk.valid),
    ]
    if out.intensity is not None and blk.intensity is not None:
        pairs.append((out.intensity, blk.intensity))
    if out.y is not None:
        pairs.append((out.y, blk.y))
    if not isinstance(pos, slice):  # profiles of several blocks interleaved (rare)
        idx = offsets[pos][:, None] + np.arange(N)
        for flat, arr in pairs:
            flat[idx] = arr if arr.ndim == 1 else arr[src]
        return
    a, b = int(offsets[pos.start]), int(offsets[pos.stop])
    for flat, arr in pairs:
        view = flat[a:b].reshape(k, N)
        if arr.ndim == 1:  # a grid shared by the block: one broadcast copy
            view[...] = arr
        elif isinstance(src, slice):
            view[...] = arr[src]
        elif arr.dtype == view.dtype:
            np.take(arr, src, axis=0, out=view, mode="clip")  # unbuffered: one copy
        else:
            view[...] = arr[src]
