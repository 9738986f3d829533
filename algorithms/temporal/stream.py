"""The streaming temporal detector, ``TemporalStream``: chunks in, final scores out (eqs. 1-17).

The same segments, windows and equations as the batch detector
(:mod:`algorithms.temporal.batch`), with identical scores for numeric sigma and max_gap; memory
is bounded per scanner (the open segment's last rows).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from algorithms.errors import NotTimeOrderedError, ParameterError
from algorithms.temporal.batch import (
    estimate_sigma,
    finite_points,
    prepare,
    result_info,
    scores_from_differences,
    unit_differences,
)
from algorithms.temporal.parameters import check_arrays, check_params
from algorithms.temporal.segments import median_positive_step, stream_windows
from algorithms.temporal.windows import window_differences


@dataclass
class _Tail:
    """What a stream keeps of one group: the open segment's last rows.

    Rows [0, n_done) were scored already and stay only as window context (at most n1 + n2 of
    them); rows [n_done, len) wait for their window to complete. ``seg_pos0`` is the position of
    row 0 in its segment (the segment may have begun in an earlier chunk).
    """

    t: np.ndarray
    xyz: np.ndarray
    index: np.ndarray
    seg_pos0: int = 0
    n_done: int = 0
    max_gap: float | None = None  # seconds; None while 'auto' is unresolved


def _split_by_group(rows: np.ndarray, group: np.ndarray | None) -> dict[int, np.ndarray]:
    """rows (r,) split by their group id, each part keeping the input order (stable sort)."""
    if group is None:
        return {0: rows} if rows.size else {}
    g = group[rows]
    order = np.argsort(g, kind="stable")
    g, rows = g[order], rows[order]
    cuts = np.flatnonzero(g[1:] != g[:-1]) + 1
    parts = np.split(rows, cuts)
    return {int(g[a]): part for a, part in zip(np.r_[0, cuts], parts, strict=True) if part.size}


class TemporalStream:
    """The ``temporal`` detector over a stream of chunks, with memory bounded per group.

    Feed successive chunks with ``push`` (points ordered by time within each group; groups may
    interleave, chunks may have any size) and call ``finish`` at the end. Both return
    ``(index, score)`` for the points whose score became final, in no particular order: a point
    is final once its window is complete (n2 later points of its segment have arrived and the
    segment is long enough) or its segment ended at a time gap. Points without a finite time or
    position come back at once with score NaN. ``critical_value`` gives the flag threshold.

    With numeric ``sigma`` and ``max_gap`` the scores equal ``detect_temporal`` on the
    concatenated input exactly. With ``'auto'`` either is resolved from the first
    ``warmup_points`` points (all of them if the stream is shorter), which are held back
    until then (with the rest of the chunk that completes them): sigma as in
    ``detect_temporal`` on those points, max_gap per group from that group's points among them
    (a group first seen later: from its first rows that hold a positive time step). The
    resolved values are in ``info``.

    ``max_gap_by_group``: each group's max_gap in seconds (inf: one segment), as
    ``detect_temporal`` resolves 'auto' over the whole series; a caller that can read the
    series twice passes them to get the batch's segments exactly. ``differences``: instead of
    scores, return each point's unit-sigma differences (m, 4): dz of eq. 15 per axis and
    sqrt(eq. 16) (NaN where untested), from which ``estimate_sigma`` and
    ``scores_from_differences`` give the batch's sigma and scores; sigma is not used then.
    ``compiled``: run the compiled smoother (the same bits; worth its import for a long
    stream), None: only when numba is loaded already (``windows.use_compiled`` per chunk).
    """

    def __init__(
        self,
        *,
        n1: int = 5,
        n2: int = 5,
        sigma: float | str | Sequence[float] = "auto",
        alpha: float = 0.001,
        max_gap: float | str = "auto",
        warmup_points: int = 200_000,
        max_gap_by_group: Mapping[int, float] | None = None,
        differences: bool = False,
        sigma_floor: float | Sequence[float] = 0.0,
        compiled: bool | None = None,
    ) -> None:
        self._p = check_params(n1, n2, sigma, alpha, max_gap)
        self._sigma_floor = np.asarray(sigma_floor, dtype=np.float64)
        self._given_gaps = None if max_gap_by_group is None else dict(max_gap_by_group)
        self._differences = bool(differences)
        self.compiled = compiled  # may change between chunks: the same bits either way
        if isinstance(warmup_points, bool) or not isinstance(warmup_points, int | np.integer):
            raise ParameterError(f"warmup_points must be an integer, got {warmup_points!r}")
        self._warmup_points = int(warmup_points)
        self._size = self._p.n1 + self._p.n2 + 1
        self._sigma: np.ndarray | None = self._p.sigma
        self._sigma_source = "given" if self._sigma is not None else "auto"
        self._resolved = self._sigma is not None and (
            self._p.max_gap is not None or self._given_gaps is not None)
        self._warmup: list[tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray]] = []
        self._warmup_count = 0
        self._tails: dict[int, _Tail] = {}
        self._gap_by_group: dict[int, float | None] = {}
        self._counts = {"points": 0, "points_tested": 0, "points_flagged": 0}
        self._segments = 0
        self._short_segments = 0
        self._finished = False

    @property
    def critical_value(self) -> float:
        """Two-sided normal critical value for alpha: a point is flagged when score > this."""
        return self._p.critical_value

    @property
    def info(self) -> dict:
        """Resolved parameters and counts so far (JSON-serialisable), as ``detect_temporal``."""
        sigma = self._sigma if self._sigma is not None else np.full(3, np.nan)
        info = result_info(self._p, sigma, self._sigma_source, self._gap_by_group)
        info.update(self._counts, segments=self._segments, segments_untested=self._short_segments)
        return info

    def push(
        self,
        xyz: np.ndarray,
        gps_time: np.ndarray,
        group: np.ndarray | None,
        index: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Add a chunk: xyz (c, 3), gps_time (c,), group (c,) ints or None, index (c,) ints.

        Returns (index, score) of the points that became final, as int64 and float64 arrays.
        """
        if self._finished:
            raise ParameterError("this TemporalStream is finished; start a new one")
        xyz, t, group = check_arrays(xyz, gps_time, group)
        index = np.asarray(index)
        if index.shape != t.shape or not np.issubdtype(index.dtype, np.integer):
            raise ParameterError(f"index must hold ({t.size},) integers, got {index.shape}")
        if not self._resolved:
            self._warmup.append((xyz, t, group, index))
            self._warmup_count += t.size
            if self._warmup_count < self._warmup_points:
                return np.zeros(0, dtype=np.int64), np.zeros(0)
            return self._end_warmup(final=False)
        return self._process(xyz, t, group, index, final=False)

    def finish(self) -> tuple[np.ndarray, np.ndarray]:
        """Flush every held-back point (the open segments end here)."""
        if self._finished:
            return np.zeros(0, dtype=np.int64), np.zeros(0)
        if not self._resolved:
            out = self._end_warmup(final=True)
        else:
            out = self._process(np.zeros((0, 3)), np.zeros(0), None, np.zeros(0, np.int64), True)
        self._finished = True
        return out

    # -- internals ---------------------------------------------------------------------------

    def _end_warmup(self, final: bool) -> tuple[np.ndarray, np.ndarray]:
        """Resolve 'auto' sigma / max_gap from the held-back points, then process them."""
        chunks = self._warmup
        self._warmup = []
        xyz = np.concatenate([c[0] for c in chunks])
        t = np.concatenate([c[1] for c in chunks])
        has_group = any(c[2] is not None for c in chunks)
        group = None
        if has_group:
            group = np.concatenate(
                [c[2] if c[2] is not None else np.zeros(c[1].size, np.int64) for c in chunks]
            )
        index = np.concatenate([c[3] for c in chunks])
        head = slice(0, self._warmup_points)  # resolve from these; the chunk may hold more
        s = prepare(xyz[head], t[head], None if group is None else group[head], self._p)
        if self._p.max_gap is None:
            self._gap_by_group.update(s.max_gap_by_group)
            for gid, gap in s.max_gap_by_group.items():
                if gap is not None:
                    self._tail(gid).max_gap = gap
        if self._sigma is None:
            dz, sdz = unit_differences(s, self._p, self.compiled)
            self._sigma, self._sigma_source = estimate_sigma(dz, sdz, self._sigma_floor)
        self._resolved = True
        return self._process(xyz, t, group, index, final)

    def _tail(self, gid: int) -> _Tail:
        if gid not in self._tails:
            gap = self._p.max_gap
            if self._given_gaps is not None and gid in self._given_gaps:
                gap = float(self._given_gaps[gid])
            self._tails[gid] = _Tail(
                np.zeros(0), np.zeros((0, 3)), np.zeros(0, np.int64), max_gap=gap
            )
        return self._tails[gid]

    def _process(
        self,
        xyz: np.ndarray,
        t: np.ndarray,
        group: np.ndarray | None,
        index: np.ndarray,
        final: bool,
    ) -> tuple[np.ndarray, np.ndarray]:
        out_index: list[np.ndarray] = []
        out_score: list[np.ndarray] = []
        valid = finite_points(xyz, t)
        if not valid.all():
            out_index.append(index[~valid].astype(np.int64))
            out_score.append(np.full((int(np.count_nonzero(~valid)), *self._width), np.nan))
        rows_by_group = _split_by_group(np.flatnonzero(valid), group)
        for gid in sorted(set(rows_by_group) | (set(self._tails) if final else set())):
            rows = rows_by_group.get(gid, np.zeros(0, dtype=np.int64))
            tail = self._tail(gid)
            idx, score = self._advance(gid, tail, t[rows], xyz[rows], index[rows], final)
            out_index.append(idx)
            out_score.append(score)
            if final:
                del self._tails[gid]
        if not out_index:
            return np.zeros(0, dtype=np.int64), np.zeros((0, *self._width))
        idx = np.concatenate(out_index).astype(np.int64, copy=False)
        score = np.concatenate(out_score)
        self._counts["points"] += idx.size
        if self._differences:
            self._counts["points_tested"] += int(np.count_nonzero(~np.isnan(score[:, 3])))
            return idx, score
        self._counts["points_tested"] += int(np.count_nonzero(~np.isnan(score)))
        self._counts["points_flagged"] += int(np.count_nonzero(score > self.critical_value))
        return idx, score

    @property
    def _width(self) -> tuple[int, ...]:
        """The shape of one point's output: () a score, (4,) its unit differences."""
        return (4,) if self._differences else ()

    def _output(self, dz: np.ndarray, sdz: np.ndarray) -> np.ndarray:
        if self._differences:
            return np.column_stack([dz, sdz])
        return scores_from_differences(dz, sdz, self._sigma)

    def _advance(
        self,
        gid: int,
        tail: _Tail,
        t_new: np.ndarray,
        xyz_new: np.ndarray,
        idx_new: np.ndarray,
        final: bool,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Append one group's rows, score the rows whose windows are complete, trim the tail."""
        t = np.concatenate([tail.t, t_new])
        if np.any(t[1:] < t[:-1]):
            raise NotTimeOrderedError(
                "TemporalStream needs points ordered by gps_time within each group"
            )
        xyz = np.concatenate([tail.xyz, xyz_new])
        index = np.concatenate([tail.index, idx_new.astype(np.int64)])
        if tail.max_gap is None:
            step = median_positive_step(t)
            if not math.isfinite(step) and not final:
                tail.t, tail.xyz, tail.index = t, xyz, index  # cannot cut segments yet
                return np.zeros(0, dtype=np.int64), np.zeros((0, *self._width))
            tail.max_gap = 5.0 * step if math.isfinite(step) else math.inf
        if gid not in self._gap_by_group:
            self._gap_by_group[gid] = tail.max_gap if math.isfinite(tail.max_gap) else None

        targets, lo, hi, done, seg_start, n_seg, n_short = stream_windows(
            t, tail.max_gap, -tail.seg_pos0, tail.n_done, self._p.n1, self._p.n2, final
        )
        self._segments += n_seg
        self._short_segments += n_short
        score = np.zeros((0, *self._width))
        if targets.size:
            dz, sdz = window_differences(t, xyz, np.empty(0), targets, lo, hi,
                                          compiled=self.compiled)
            score = self._output(dz, sdz)
        # Keep the open segment's pending rows and up to n1 + n2 rows of context before them.
        n = t.size
        keep = n if final else max(0, seg_start, done - (self._size - 1))
        tail.t, tail.xyz, tail.index = t[keep:], xyz[keep:], index[keep:]
        tail.seg_pos0 = keep - seg_start
        tail.n_done = done - keep
        return index[targets], score
