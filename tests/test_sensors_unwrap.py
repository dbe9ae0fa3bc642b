"""Counter unwrap across calls and gap accounting."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from timedexec.errors import ConfigError
from timedexec.sensors import CounterUnwrapper, unwrap_counter

WRAP = 65536


def _feed(unwrapper: CounterUnwrapper, counter: np.ndarray, chunks: list[int], **kw):  # type: ignore[no-untyped-def]
    out, keep = [], []
    pos = 0
    i = 0
    while pos < counter.shape[0]:
        size = chunks[i % len(chunks)]
        res = unwrapper.update(counter[pos : pos + size].astype(np.uint16), **kw)
        out.append(res.index)
        keep.append(res.keep)
        pos += size
        i += 1
    return np.concatenate(out), np.concatenate(keep)


def _longest_run(flags: np.ndarray) -> int:
    """Length of the longest run of True in a boolean array."""
    padded = np.concatenate(([0], flags.astype(np.int8), [0]))
    edges = np.flatnonzero(np.diff(padded))
    return int((edges[1::2] - edges[::2]).max()) if edges.size else 0


def test_long_gap_at_chunk_end_costs_one_frame() -> None:
    """A gap longer than max_step needs the next frame to confirm it. When the first frame
    after the gap ends a chunk (hypothesis found drops merging into 4096 missing samples
    with chunks of 100), that frame is dropped and counted; the next chunk confirms the
    jump and every later index is right."""
    kept = np.concatenate((np.arange(0, 100), np.arange(4196, 4600)))
    unwrapper = CounterUnwrapper()
    index, keep = _feed(unwrapper, kept % WRAP, [101])
    assert not keep[100]
    assert keep[:100].all()
    assert keep[101:].all()
    np.testing.assert_array_equal(index, np.delete(kept, 100))
    assert unwrapper.dropped_frames == 1
    # the gap runs from sample 100 to the first accepted frame after it (4197)
    assert unwrapper.missing_samples == 4197 - 100


def test_unwrap_over_several_wraps_in_random_chunks() -> None:
    """Five wraps (41 s at 8 kHz) fed in uneven chunks unwrap to the true sample index."""
    k = np.arange(40_000, 40_000 + 5 * WRAP + 123)
    index, keep = _feed(CounterUnwrapper(), k % WRAP, [1, 700, 4000, 13])
    assert keep.all()
    np.testing.assert_array_equal(index, k)  # first index = first counter = k[0]
    assert index[-1] - index[0] == k[-1] - k[0]


def test_gaps_are_counted_with_positions() -> None:
    """Missing samples (including a gap across a wrap) show up as gaps at the right index."""
    k = np.arange(2 * WRAP)
    missing = np.r_[10, 11, 12, 500, WRAP - 2 : WRAP + 3, 100_000]
    kept = np.setdiff1d(k, missing)
    unwrapper = CounterUnwrapper()
    index, _ = _feed(unwrapper, kept % WRAP, [64])
    np.testing.assert_array_equal(index, kept)
    starts, counts = unwrapper.gaps
    np.testing.assert_array_equal(starts, [10, 500, WRAP - 2, 100_000])
    np.testing.assert_array_equal(counts, [3, 1, 5, 1])
    assert unwrapper.missing_samples == missing.shape[0]
    assert unwrapper.gap_count == 4


def test_a_corrupted_counter_is_dropped_not_followed() -> None:
    """A frame with a wrong counter (passed the CRC by chance) is dropped and counted; the
    index does not jump, and the sample that frame carried becomes a one-sample gap."""
    counter = np.arange(100) % WRAP
    counter[40] = 31_000  # a forward jump the next frame does not confirm
    counter[70] = 69  # a duplicate of the previous counter
    unwrapper = CounterUnwrapper()
    index, keep = _feed(unwrapper, counter, [25])
    assert keep.sum() == 98
    assert not keep[40]
    assert not keep[70]
    np.testing.assert_array_equal(index, np.delete(np.arange(100), [40, 70]))
    assert unwrapper.dropped_frames == 2
    np.testing.assert_array_equal(unwrapper.gaps[0], [40, 70])
    np.testing.assert_array_equal(unwrapper.gaps[1], [1, 1])


def test_sensor_reset_is_a_confirmed_discontinuity() -> None:
    """The counter restarting at 0 (sensor reset) is accepted once the next frame confirms
    it; indices keep increasing and the discontinuity is reported."""
    counter = np.r_[np.arange(30_000, 30_100), np.arange(0, 50)]
    unwrapper = CounterUnwrapper()
    result = unwrapper.update(counter.astype(np.uint16))
    assert result.discontinuity
    assert unwrapper.discontinuities == 1
    assert result.keep.all()
    assert np.all(np.diff(result.index) == 1)


def test_long_silence_is_bridged_with_arrival_times() -> None:
    """A 20 s dropout (more than two wraps) is unwrapped correctly from arrival times."""
    rate = 8000.0
    unwrapper = CounterUnwrapper(nominal_rate_hz=rate)
    k1 = np.arange(1000)
    unwrapper.update((k1 % WRAP).astype(np.uint16), k1 / rate)
    k2 = np.arange(1000 + 160_000, 1000 + 160_000 + 500)
    result = unwrapper.update((k2 % WRAP).astype(np.uint16), k2 / rate + 0.003)
    np.testing.assert_array_equal(result.index, k2)
    assert unwrapper.missing_samples == 160_000


def test_unwrap_counter_offline() -> None:
    """The offline helper unwraps a recorded sequence and checks its start argument."""
    k = np.arange(70_000, 200_000, 7)
    np.testing.assert_array_equal(unwrap_counter(k % WRAP, start=70_000), k)
    np.testing.assert_array_equal(unwrap_counter(k % WRAP), k - 65536)
    assert unwrap_counter([]).shape == (0,)
    with pytest.raises(ConfigError, match="congruent"):
        unwrap_counter([5, 6], start=7)


def test_bad_parameters() -> None:
    """Invalid settings name the value and the allowed range."""
    with pytest.raises(ConfigError, match="max_step=0"):
        CounterUnwrapper(max_step=0)
    with pytest.raises(ConfigError, match="nominal_rate_hz=-1"):
        CounterUnwrapper(nominal_rate_hz=-1)


@settings(max_examples=60, deadline=None, derandomize=True)
@given(
    start=st.integers(0, WRAP - 1),
    drops=st.lists(st.integers(1, 3000), max_size=20),
    chunks=st.lists(st.integers(1, 5000), min_size=1, max_size=5).filter(
        lambda c: sum(c) >= 100 * len(c)
    ),
    data=st.data(),
)
def test_fuzz_unwrap_matches_truth(
    start: int, drops: list[int], chunks: list[int], data: st.DataObject
) -> None:
    """Random gaps (each shorter than max_step) and random chunking: every kept frame gets
    its true index and the missing count equals the number of dropped samples."""
    total = 2 * WRAP + 5000
    k = np.arange(start, start + total)
    positions = data.draw(st.lists(st.integers(1, total - 4000), max_size=len(drops)))
    mask = np.ones(total, dtype=bool)
    for pos, length in zip(positions, drops, strict=False):
        mask[pos : pos + length] = False
    # Overlapping drops merge into one gap; keep every merged gap below max_step (the
    # premise), since a longer one needs the next frame's confirmation, which a chunk end
    # cannot give (that case is pinned by test_long_gap_at_chunk_end_costs_one_frame).
    assume(_longest_run(~mask) < CounterUnwrapper().max_step)
    kept = k[mask]
    unwrapper = CounterUnwrapper()
    index, keep = _feed(unwrapper, kept % WRAP, chunks)
    assert keep.all()
    np.testing.assert_array_equal(index, kept)
    assert unwrapper.missing_samples == int((~mask[: np.flatnonzero(mask)[-1]]).sum()) - int(
        (~mask[: np.flatnonzero(mask)[0]]).sum()
    )
