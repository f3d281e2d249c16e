"""An incremental place index over ORB binary descriptors: candidate database frames per query.

The detector's SAD search compares a query with every older frame. This index proposes a few
candidate frames instead, at a cost per query that does not grow with the log. It follows
iBoW-LCD / OBIndex2 (Garcia-Fidalgo and Ortiz, 2018): a bag of binary words built online with
no training, an inverted index scored by tf-idf, and islands of temporally close candidates.
Where it differs, it says why.

Vocabulary. A descriptor joins its nearest word when that word is within `radius` bits
(Hamming); otherwise it becomes a new word, whose descriptor is that first descriptor. Words
are not merged (OBIndex2 can AND/OR them): a merged word would change its hash keys. A frame's
descriptors are matched against the vocabulary as it was before the frame, so two similar
descriptors of one frame make two words.

Nearest-word search: multi-index hashing (Norouzi, Punjani and Fleet, 2012). The 256 bits are
cut into 16 substrings of 16 bits, and substring t's value is a key into table t. A word within
r < 16 bits of a descriptor agrees with it exactly on at least one substring (pigeonhole), and
at ORB match distances (25-40 bits) it still often does, so with all 16 tables the index finds
most of the nearest words a brute force would (fewer tables find fewer). Each bucket holds
`bucket_slots` words, so a lookup reads at most 16 x bucket_slots words whatever the
vocabulary's size. A new word takes an empty slot, else the slot of the bucket's least observed
word (smallest df, then oldest): a landmark seen on several frames or visits outlives one seen
once. A word pushed out of every bucket can no longer be found and is freed, so the vocabulary
is at most the number of slots.

Unstable words. As in iBoW-LCD, a word seen in fewer than `min_frames` frames by the time it is
`purge_age` frames old is removed: sensor noise, or a feature too unstable to be seen again on a
revisit. That keeps the vocabulary small at almost no cost in the places found.

Scoring. A frame holds tf(w) = (its descriptors on word w) / (its descriptors). Database frame
f scores sum_w idf(w) min(tf_q(w), tf_f(w)) over the words it shares with the query q: the
intersection of the two tf-idf histograms, which for L1-normalized vectors is DBoW2's L1 score
1 - |a - b|_1 / 2. It is divided by the query's own mass sum_w idf(w) tf_q(w), so the score is
the share of the query found in f, in [0, 1]; the query's unmatched descriptors count in that
mass as words seen once. idf(w) = log(N / df(w)), with N the frames added and df(w) the frames
the word appeared in, both current: old frames need no rescoring as the log grows.

Posting cap. A word's postings are walked newest first, at most `posting_cap` of them.
Dropping the words whose lists outgrow a cap, as stop words, would on a route driven lap after
lap end up dropping every landmark; instead a frequent word keeps its newest postings (the
latest visit of a place is as good a loop closure as the first) and idf weighs it down. Older
postings can never be read again, nor can those of a freed word: when the postings' arrays are
full they are dropped first (`_Postings.compact`), the rest keeping their order, so results do
not change.

Cost. A query of n descriptors reads at most n x tables x bucket_slots words and
n x posting_cap postings, however long the log; only a binary search over the frames grows
(log N). The lists are walked in lockstep, one vectorized step per depth, and the postings
found are sorted once, which orders them by frame for the scoring.

Memory. What grows per frame: `FRAME_BYTES`, and the postings a query can still read, at most
`POSTING_BYTES` per distinct word of the frame (up to twice that allocated, as capacities
double); those of words purged or pushed out of their buckets, and those beyond the newest
`posting_cap` of a word, are dropped. The rest is capped
(`PlaceIndexParams.fixed_bytes`): the hash tables have a fixed size, and the vocabulary is at
most the number of slots. `memory_bound` states both.

Determinism. There is no randomness; ties break by word id and by frame index.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

Descriptors = npt.NDArray[np.uint8]
IntArray = npt.NDArray[np.int64]
FloatArray = npt.NDArray[np.float64]
UIntArray = npt.NDArray[np.unsignedinteger]

DESCRIPTOR_BYTES = 32  # ORB: 256 bits
LANES = DESCRIPTOR_BYTES // 8  # a descriptor as 64-bit integers, for the processor's popcount
KEY_BITS = 16  # one little-endian uint16 of the descriptor per table
MAX_TABLES = DESCRIPTOR_BYTES * 8 // KEY_BITS
BUCKETS = 1 << KEY_BITS
# Per posting: the next (older) posting of the same word, int32, and the count of the frame's
# descriptors on the word, uint8. Per frame: the caller's index, first posting, descriptor count.
POSTING_BYTES = 4 + 1
FRAME_BYTES = 8 + 8 + 2
# Per word: descriptor, newest posting, document frequency, birth frame, slots held, free list.
WORD_BYTES = DESCRIPTOR_BYTES + 4 + 4 + 4 + 1 + 4
MAX_POSTINGS = int(np.iinfo(np.int32).max)  # int32 links: about 5 million frames of 400 words
INITIAL_ROWS = 16  # a growable array's first capacity
NO_POSTING = 0  # the sentinel posting: the head of an empty list, and its own next
_EMPTY = -1  # an empty bucket slot; no word
_FAR = DESCRIPTOR_BYTES * 8 + 1  # a distance beyond any Hamming distance: empty slots
_NO_WORD = int(np.iinfo(np.int32).max)  # above every word id, for the smallest-id tie-break

_POPCOUNT = np.array([bin(i).count("1") for i in range(256)], dtype=np.uint8)


def popcount(values: UIntArray) -> npt.NDArray[np.uint8]:
    """Set bits of each element of an unsigned integer array."""
    if hasattr(np, "bitwise_count"):  # NumPy >= 2.0: the processor's popcount instruction
        counts: npt.NDArray[np.uint8] = np.bitwise_count(values)
        return counts
    as_bytes = np.ascontiguousarray(values).view(np.uint8)  # pragma: no cover - NumPy 1.x
    per_byte = _POPCOUNT[as_bytes].reshape(*values.shape, values.itemsize)  # pragma: no cover
    summed: npt.NDArray[np.uint8] = per_byte.sum(axis=-1, dtype=np.uint8)  # pragma: no cover
    return summed  # pragma: no cover


def hamming(a: Descriptors, b: Descriptors) -> IntArray:
    """Hamming distances between uint8 descriptors along the last axis (broadcasting)."""
    distances: IntArray = popcount(np.bitwise_xor(a, b)).sum(axis=-1, dtype=np.int64)
    return distances


@dataclass(frozen=True)
class PlaceIndexParams:
    """Place index parameters; the defaults are measured by tools/bench/place_index.py.

    radius: a descriptor joins its nearest word when within this many bits, else starts one.
    tables: 16-bit substrings hashed (1..16); fewer is faster and finds fewer words.
    bucket_slots: words kept per bucket (the vocabulary's cap is 65,536 x tables x this).
    posting_cap: newest postings read per query word (those of frames not older than the
        query's `before` included: they are read, then skipped).
    purge_age, min_frames: a word seen in fewer than `min_frames` frames by the time it is
        `purge_age` frames old is removed (min_frames = 1 keeps them all).
    max_descriptors: descriptors used per frame, the first ones.
    island_gap: results whose frame indices are at most this far apart form one island,
        scored by the sum of its frames' scores and represented by its best frame (0: none).
    island_candidates: how many of the best frames are grouped into islands.
    """

    radius: int = 40
    tables: int = MAX_TABLES
    bucket_slots: int = 4
    posting_cap: int = 32
    purge_age: int = 8
    min_frames: int = 2
    max_descriptors: int = 1000
    island_gap: int = 0
    island_candidates: int = 50

    def __post_init__(self) -> None:
        if not 0 <= self.radius <= DESCRIPTOR_BYTES * 8:
            raise ValueError(f"radius must be in 0..{DESCRIPTOR_BYTES * 8}, got {self.radius}")
        if not 1 <= self.tables <= MAX_TABLES:
            raise ValueError(f"tables must be in 1..{MAX_TABLES}, got {self.tables}")
        if not 1 <= self.bucket_slots <= 255:
            raise ValueError(f"bucket_slots must be in 1..255, got {self.bucket_slots}")
        if not 1 <= self.max_descriptors <= np.iinfo(np.uint16).max:
            raise ValueError(f"max_descriptors must be in 1..65535, got {self.max_descriptors}")
        for name in ("posting_cap", "purge_age", "min_frames", "island_candidates"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.island_gap < 0:
            raise ValueError(f"island_gap must be >= 0, got {self.island_gap}")

    @property
    def max_words(self) -> int:
        """The vocabulary's bound: every live word holds a slot, and one frame's new words
        can exist before the slots they push others out of are counted."""
        return self.tables * BUCKETS * self.bucket_slots + self.max_descriptors

    @property
    def fixed_bytes(self) -> int:
        """The most the index holds apart from what grows per frame: the tables, the
        vocabulary at its bound, and the new words of the last `purge_age` frames."""
        tables = self.tables * BUCKETS * 4 * self.bucket_slots
        recent = (self.purge_age + 1) * self.max_descriptors * 8
        return tables + self.max_words * WORD_BYTES + recent


def memory_bound(params: PlaceIndexParams, frames: int) -> int:
    """The most `PlaceIndex.memory_bytes` can be after `frames` frames: the fixed part, plus
    per frame FRAME_BYTES and POSTING_BYTES per descriptor, twice (capacities double)."""
    per_frame = FRAME_BYTES + params.max_descriptors * POSTING_BYTES
    return params.fixed_bytes + 2 * frames * per_frame + INITIAL_ROWS * per_frame


class _Growable:
    """A NumPy array appended to at the end (rows of `width` values when width > 0); its
    capacity doubles, up to `limit` rows."""

    def __init__(self, dtype: type[np.generic], limit: int | None = None, width: int = 0) -> None:
        self.data: npt.NDArray[Any] = np.zeros(
            (INITIAL_ROWS, width) if width else INITIAL_ROWS, dtype=dtype
        )
        self.size = 0
        self.limit = limit

    def extend(self, values: npt.ArrayLike) -> IntArray:
        """Append values; returns their positions. MemoryError beyond the limit."""
        values = np.asarray(values)
        need = self.size + len(values)
        if need > len(self.data):
            self._grow(need)
        start, self.size = self.size, need
        self.data[start:need] = values
        return np.arange(start, need, dtype=np.int64)

    def _grow(self, need: int) -> None:
        if self.limit is not None and need > self.limit:
            raise MemoryError(f"place index: more than {self.limit} entries")
        capacity = max(need, 2 * len(self.data))
        if self.limit is not None:
            capacity = min(capacity, self.limit)
        grown = np.zeros((capacity, *self.data.shape[1:]), dtype=self.data.dtype)
        grown[: self.size] = self.data[: self.size]
        self.data = grown

    def reserve(self, capacity: int) -> None:
        """Room for at least `capacity` rows (up to the limit) without growing again."""
        if capacity > len(self.data):
            self._grow(capacity)

    def keep(self, mask: npt.NDArray[np.bool_]) -> None:
        """Keep only the rows where `mask` (one per row held) is set, in their order."""
        kept = self.data[: self.size][mask]
        self.size = len(kept)
        self.data[: self.size] = kept

    @property
    def view(self) -> npt.NDArray[Any]:
        return self.data[: self.size]

    @property
    def nbytes(self) -> int:
        return int(self.data.nbytes)


class _Vocabulary:
    """The words, their hash tables and their per-word counters (df, newest posting)."""

    def __init__(self, params: PlaceIndexParams) -> None:
        self.params = p = params
        self.slots = np.full((p.tables * BUCKETS, p.bucket_slots), _EMPTY, dtype=np.int32)
        # Descriptors as rows of 64-bit lanes: a gathered word is one cache line.
        self.desc = _Growable(np.uint64, p.max_words, width=LANES)
        self.head = _Growable(np.int32, p.max_words)  # newest posting (NO_POSTING: none)
        self.df = _Growable(np.int32, p.max_words)  # frames the word appeared in
        self.born = _Growable(np.int32, p.max_words)  # frame position it was created at
        self.refs = _Growable(np.uint8, p.max_words)  # slots holding it
        self.free = _Growable(np.int32, p.max_words)  # ids to reuse, last freed on top

    @property
    def columns(self) -> list[_Growable]:
        return [self.desc, self.head, self.df, self.born, self.refs, self.free]

    @property
    def count(self) -> int:
        return self.head.size - self.free.size

    def buckets(self, desc: Descriptors) -> IntArray:
        """(n, tables) bucket rows: table t's key is the descriptor's t-th little-endian uint16."""
        keys = desc.view("<u2")[:, : self.params.tables].astype(np.int64)
        return keys + np.arange(self.params.tables, dtype=np.int64) * BUCKETS

    def nearest(self, desc: Descriptors) -> IntArray:
        """Each descriptor's nearest word among its buckets' words if within radius, else -1.

        Ties go to the smallest word id, so they cannot depend on the order of the slots.
        """
        if len(desc) == 0:
            return np.zeros(0, dtype=np.int64)
        slots = np.take(self.slots, self.buckets(desc), axis=0).reshape(len(desc), -1)
        candidates = slots.astype(np.intp)  # NumPy gathers with int32 indices several times slower
        distance = self._distances(desc, candidates)
        distance[candidates < 0] = _FAR
        best = distance.min(axis=1)
        word = np.where(distance == best[:, None], candidates, _NO_WORD).min(axis=1)
        return np.where(best <= self.params.radius, word, _EMPTY).astype(np.int64)

    def _distances(self, desc: Descriptors, words: IntArray) -> npt.NDArray[np.int16]:
        """Hamming distances (n, m) between descriptor i and words[i, j] (an empty slot, -1,
        reads the last row of the array: the caller masks it)."""
        gathered = np.take(self.desc.data, words, axis=0)  # (n, m, lanes)
        np.bitwise_xor(gathered, desc.view(np.uint64)[:, None, :], out=gathered)
        bits = popcount(gathered)
        # Lane by lane: a sum along the short last axis is several times slower in NumPy.
        total = bits[..., 0].astype(np.int16)
        for lane in range(1, LANES):
            total += bits[..., lane]
        return total

    def descriptors(self, ids: IntArray) -> Descriptors:
        """The words' descriptors as (n, 32) uint8."""
        return np.take(self.desc.data, ids, axis=0).view(np.uint8)

    def allocate(self, desc: Descriptors, position: int) -> IntArray:
        """Ids for new words (freed ones first, last freed first), not yet in any bucket."""
        reused = min(len(desc), self.free.size)
        ids = self.free.view[self.free.size - reused :][::-1].astype(np.int64)
        self.free.size -= reused
        fresh = len(desc) - reused
        if fresh:  # every per-word column grows by the same rows
            new = self.head.extend(np.zeros(fresh, dtype=np.int32))
            for column in (self.desc, self.df, self.born, self.refs):
                column.extend(np.zeros((fresh, *column.data.shape[1:]), dtype=column.data.dtype))
            ids = np.concatenate([ids, new])
        self.desc.data[ids] = desc.view(np.uint64)
        self.head.data[ids] = NO_POSTING
        self.df.data[ids] = 0
        self.born.data[ids] = position
        self.refs.data[ids] = 0
        return ids

    def insert(self, ids: IntArray, desc: Descriptors) -> None:
        """Put new words in their buckets and free the words left in none.

        A full bucket drops its least observed word (smallest df, then the oldest): a
        landmark seen on several frames or visits outlives a word seen once, so a place
        revisited is remembered longer than one passed once.
        """
        if len(ids) == 0:
            return
        rows, owners, victim = self._placement(ids, desc)
        evicted = self.slots[rows, victim].astype(np.int64)
        evicted = evicted[evicted >= 0]
        np.subtract.at(self.refs.data, evicted, 1)
        self.slots[rows, victim] = owners
        np.add.at(self.refs.data, owners, 1)
        dead = np.unique(np.concatenate([evicted, ids]))
        self.release(dead[self.refs.data[dead] == 0])

    def _placement(self, ids: IntArray, desc: Descriptors) -> tuple[IntArray, IntArray, IntArray]:
        """(bucket row, word, slot) of each insertion. The r-th new word of a bucket takes its
        r-th victim, so no slot is written twice (NumPy keeps an unspecified one of repeated
        writes); words beyond `bucket_slots` in one bucket skip it (they are in others)."""
        rows = self.buckets(desc).ravel()
        owners = np.repeat(ids, self.params.tables)
        order = np.argsort(rows, kind="stable")  # descriptor order within a bucket
        rows, owners = rows[order], owners[order]
        starts = np.r_[True, rows[1:] != rows[:-1]]
        group = np.cumsum(starts) - 1
        rank = np.arange(len(rows)) - np.flatnonzero(starts)[group]
        victims = self._victims(rows[starts])
        keep = rank < self.params.bucket_slots
        rows, owners, group, rank = rows[keep], owners[keep], group[keep], rank[keep]
        return rows, owners, victims[group, rank]

    def _victims(self, rows: IntArray) -> IntArray:
        """Each bucket's slots in the order they are given up: empty ones, then the least
        observed, oldest words."""
        occupants = np.take(self.slots, rows, axis=0).astype(np.intp)
        df = np.take(self.df.data, occupants).astype(np.int64)
        born = np.take(self.born.data, occupants).astype(np.int64)
        key = np.where(occupants < 0, -1, df << 32 | born)
        return np.argsort(key, axis=1, kind="stable")

    def purge(self, ids: IntArray, position: int) -> None:
        """Remove the words born at frame `position` seen in fewer than `min_frames` frames."""
        ids = ids[self.born.data[ids] == position]  # not freed and reused since
        ids = ids[self.df.data[ids] < self.params.min_frames]
        if len(ids) == 0:
            return
        rows = self.buckets(self.descriptors(ids))
        word, table, column = np.nonzero(np.take(self.slots, rows, axis=0) == ids[:, None, None])
        self.slots[rows[word, table], column] = _EMPTY
        self.refs.data[ids] = 0
        self.release(ids)

    def release(self, ids: IntArray) -> None:
        """Free words no bucket holds: their postings are dropped and their ids reused."""
        if len(ids) == 0:
            return
        self.head.data[ids] = NO_POSTING
        self.df.data[ids] = 0
        self.born.data[ids] = _EMPTY
        self.free.extend(ids.astype(np.int32))


class _Postings:
    """The inverted index: per word a list of postings, newest first, linked through one
    append-only array. Posting 0 is a sentinel linked to itself, the head of every empty list,
    so the lists of a query are walked in lockstep without checking where each one ends."""

    def __init__(self) -> None:
        self.next = _Growable(np.int32, MAX_POSTINGS)  # the word's previous posting
        self.count = _Growable(np.uint8, MAX_POSTINGS)  # frame descriptors on the word
        self.frame_index = _Growable(np.int64)  # the caller's index of each frame
        self.frame_start = _Growable(np.int64)  # each frame's first posting
        self.frame_size = _Growable(np.uint16)  # each frame's descriptor count
        self.next.extend([NO_POSTING])
        self.count.extend([0])

    @property
    def columns(self) -> list[_Growable]:
        return [self.next, self.count, self.frame_index, self.frame_start, self.frame_size]

    def add_frame(
        self, frame_index: int, words: IntArray, vocabulary: _Vocabulary, cap: int
    ) -> None:
        """Prepend a posting of the new frame to the list of each of its distinct words.

        When they do not fit, the postings no query can read any more are dropped first
        (`compact`), and the arrays grow only when half of them is still held after that: a
        compaction comes after at least half a capacity of new postings, so its cost per
        posting is bounded, and memory follows what can be read, not what was ever added.
        """
        unique, counts = np.unique(words, return_counts=True)
        if self.next.size + len(unique) > len(self.next.data):
            self.compact(vocabulary, cap)
            room = max(2 * (self.next.size + len(unique)), len(self.next.data))
            self.next.reserve(room)
            self.count.reserve(room)
        self.frame_start.extend([self.next.size])
        self.frame_index.extend([frame_index])
        self.frame_size.extend([len(words)])
        entries = self.next.extend(vocabulary.head.data[unique])
        self.count.extend(np.minimum(counts, 255))
        vocabulary.head.data[unique] = entries
        vocabulary.df.data[unique] += 1

    def readable(self, vocabulary: _Vocabulary, cap: int) -> npt.NDArray[np.bool_]:
        """Per posting: whether a query can still read it, that is whether it is among the
        newest `cap` of a live word's list (the sentinel included). Postings are only ever
        prepended and a freed word's list is emptied, so one that is not can never be again."""
        readable = np.zeros(self.next.size, dtype=bool)
        readable[NO_POSTING] = True
        entries = vocabulary.head.view.astype(np.int64)
        for _ in range(cap):
            entries = entries[entries != NO_POSTING]
            if len(entries) == 0:
                break
            readable[entries] = True
            entries = np.take(self.next.data, entries).astype(np.int64)
        return readable

    def compact(self, vocabulary: _Vocabulary, cap: int) -> None:
        """Drop the postings no query can read (`readable`) and number the rest in order.

        Order is kept, so postings stay sorted by frame and queries sum the same terms in the
        same order: every result is the same, bit for bit. A kept posting whose older neighbour
        was dropped ends its list (a query never reads that far). A frame left with no posting
        starts where the next frame does, so `frames_of` still finds each posting's frame.
        """
        readable = self.readable(vocabulary, cap)
        # Kept postings before each one (its new number when kept); int32 as the links are.
        before = np.zeros(len(readable) + 1, dtype=np.int32)
        np.cumsum(readable, dtype=np.int32, out=before[1:])
        links = self.next.view[readable]
        self.next.keep(readable)
        self.count.keep(readable)
        self.next.view[:] = np.where(readable[links], before[links], NO_POSTING)
        heads = vocabulary.head.view
        heads[:] = before[heads]
        self.frame_start.view[:] = before[self.frame_start.view]

    def walk(self, heads: IntArray, cap: int, limit: int) -> tuple[IntArray, IntArray]:
        """(list number, posting) pairs of the newest `cap` postings of each list that are
        below posting `limit` (older frames), sorted by posting, that is by frame."""
        steps = np.zeros((cap, len(heads)), dtype=np.int64)
        entries = heads.astype(np.int64)
        for depth in range(cap):
            if not entries.any():  # every list ended
                break
            steps[depth] = entries
            entries = np.take(self.next.data, entries).astype(np.int64)
        keep = (steps != NO_POSTING) & (steps < limit)
        rows, found = np.nonzero(keep)[1], steps[keep]
        order = np.argsort(found)  # postings are distinct: no tie to break
        return rows[order], found[order]

    def frames_of(self, entries: IntArray) -> IntArray:
        """The frame position of each posting (entries sorted: the search is then linear)."""
        return np.searchsorted(self.frame_start.view, entries, side="right") - 1


class PlaceIndex:
    """Frames' ORB descriptors in, the best older frames for a query out.

    `add` frames in increasing `frame_index` order and `query` at any time (module docstring:
    the design). Pure computation, no I/O.
    """

    def __init__(self, params: PlaceIndexParams | None = None) -> None:
        self.params = params or PlaceIndexParams()
        self._vocabulary = _Vocabulary(self.params)
        self._postings = _Postings()
        self._recent: deque[IntArray] = deque()  # words born in each of the last frames

    @property
    def frame_count(self) -> int:
        return self._postings.frame_index.size

    @property
    def word_count(self) -> int:
        """Live words."""
        return self._vocabulary.count

    @property
    def posting_count(self) -> int:
        return self._postings.next.size - 1  # the sentinel aside

    @property
    def memory_bytes(self) -> int:
        """Bytes of every array held, at its allocated capacity."""
        v = self._vocabulary
        arrays = int(v.slots.nbytes) + sum(int(ids.nbytes) for ids in self._recent)
        return arrays + sum(c.nbytes for c in [*v.columns, *self._postings.columns])

    def words_of(self, descriptors: Descriptors) -> IntArray:
        """The word each descriptor would join, -1 for none (ids are reused once freed)."""
        return self._vocabulary.nearest(self._checked(descriptors))

    def add(self, frame_index: int, descriptors: Descriptors) -> None:
        """Add a frame: its descriptors join their nearest words or start new ones.

        Raises ValueError for descriptors that are not (n, 32) uint8, or a frame index not
        greater than the previous one.
        """
        desc = self._checked(descriptors)
        frames = self._postings.frame_index
        if frames.size and frame_index <= int(frames.data[frames.size - 1]):
            last = int(frames.data[frames.size - 1])
            raise ValueError(f"frame indices must increase: {frame_index} after {last}")
        position = self.frame_count
        vocabulary = self._vocabulary
        words = vocabulary.nearest(desc)
        unmatched = words < 0
        born = vocabulary.allocate(desc[unmatched], position)
        words[unmatched] = born
        self._postings.add_frame(frame_index, words, vocabulary, self.params.posting_cap)
        # Postings first, then the buckets: inserting may free a word this frame uses, and
        # freeing drops the word's postings, this frame's included.
        vocabulary.insert(born, desc[unmatched])
        self._recent.append(born)
        if len(self._recent) > self.params.purge_age:
            vocabulary.purge(self._recent.popleft(), position - self.params.purge_age)

    def _checked(self, descriptors: Descriptors) -> Descriptors:
        desc = np.asarray(descriptors)
        if desc.dtype != np.uint8 or desc.ndim != 2 or desc.shape[1] != DESCRIPTOR_BYTES:
            raise ValueError(
                f"descriptors must be (n, {DESCRIPTOR_BYTES}) uint8, got {desc.shape} {desc.dtype}"
            )
        return np.ascontiguousarray(desc[: self.params.max_descriptors])

    def query(self, descriptors: Descriptors, before: int, k: int) -> list[tuple[int, float]]:
        """The best k database frames with frame index < `before`, best first.

        Returns (frame index, score) pairs. A frame's score is the share of the query's
        tf-idf mass it holds, in [0, 1]; with islands, the sum over the island's frames. Ties
        go to the older frame. The index is not changed.
        """
        desc = self._checked(descriptors)
        if k < 1 or len(desc) == 0 or self.frame_count == 0:
            return []
        words = self._vocabulary.nearest(desc)
        unique, counts = np.unique(words[words >= 0], return_counts=True)
        n = self.frame_count
        df = np.maximum(self._vocabulary.df.data[unique], 1).astype(np.float64)
        idf = np.log(n / df)
        tf = counts / len(desc)
        # An unmatched descriptor would become a word seen once: idf log(n).
        mass = float(np.sum(idf * tf)) + float(np.mean(words < 0)) * np.log(n)
        if mass <= 0.0:  # a single frame so far: every idf is 0
            return []
        useful = idf > 0
        positions, scores = self._scores(unique[useful], tf[useful], idf[useful], before)
        scores /= mass
        if self.params.island_gap:
            positions, scores = self._islands(positions, scores)
        best = np.lexsort((positions, -scores))[:k]
        frames = self._postings.frame_index.view[positions[best]]
        return [(int(f), float(s)) for f, s in zip(frames, scores[best], strict=True)]

    def _scores(
        self, words: IntArray, tf: FloatArray, idf: FloatArray, before: int
    ) -> tuple[IntArray, FloatArray]:
        """The frame positions (sorted) with frame index < before that share a word with the
        query, and their tf-idf intersections with it."""
        postings = self._postings
        # Frame indices increase, so the eligible frames, and their postings, are a prefix.
        eligible = int(np.searchsorted(postings.frame_index.view, before, side="left"))
        if eligible == 0:
            return np.zeros(0, dtype=np.int64), np.zeros(0)
        limit = (
            int(postings.frame_start.data[eligible])
            if eligible < self.frame_count
            else MAX_POSTINGS
        )
        heads = np.take(self._vocabulary.head.data, words)
        rows, entries = postings.walk(heads, self.params.posting_cap, limit)
        positions = postings.frames_of(entries)
        counts = np.take(postings.count.data, entries)
        tf_frame = counts / np.take(postings.frame_size.data, positions)
        weight = idf[rows] * np.minimum(tf[rows], tf_frame)
        if len(positions) == 0:
            return positions, weight
        starts = np.flatnonzero(np.r_[True, positions[1:] != positions[:-1]])
        return positions[starts], np.add.reduceat(weight, starts)

    def _islands(self, positions: IntArray, scores: FloatArray) -> tuple[IntArray, FloatArray]:
        """Group the best frames whose indices are within island_gap into islands.

        An island scores the sum of its frames' scores (a place seen in several consecutive
        frames is a likelier revisit than one frame sharing a few words), and is represented
        by its best frame.
        """
        if len(positions) == 0:
            return positions, scores
        top = np.sort(np.lexsort((positions, -scores))[: self.params.island_candidates])
        positions, scores = positions[top], scores[top]
        frames = self._postings.frame_index.view[positions]
        starts = np.flatnonzero(np.r_[True, np.diff(frames) > self.params.island_gap])
        island = np.repeat(np.arange(len(starts)), np.diff(np.r_[starts, len(frames)]))
        order = np.lexsort((positions, -scores, island))  # each island's best frame first
        leaders = order[np.r_[True, island[order][1:] != island[order][:-1]]]
        return positions[leaders], np.add.reduceat(scores, starts)
