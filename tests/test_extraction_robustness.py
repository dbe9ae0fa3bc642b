"""Extraction on recordings made independently of timedexec.sim (tests/independent_sweep.py:
IIR sensor filter, compliant joint, USB blocks with jitter, loss and duplicates, drifting
oscillator). Small sweeps (48 trials) keep this fast; benchmarks/bench_extract_robustness.py
measures the same claims on 300 trials per condition."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from independent_sweep import Conditions, write_independent_sweep
from timedexec.extraction import extract_recording, ladder_cap
from timedexec.sensors import (
    fit_clock_drifting,
    fit_clock_lower_envelope,
    relative_counter_rows,
)

N = 48


def _score(t: Any) -> tuple[float, float, float, float]:
    """Actuation and response RMSE (s), flagged fraction and actuation 95 % coverage of an
    extraction table."""
    ok = np.array([not f for f in t["flag"]])
    e = (t["actuation_delay"] - t["true_actuation_delay"])[ok]
    r = (t["response_delay"] - t["true_response_delay"])[ok]
    cover = np.mean(np.abs(e) <= 1.96 * t["actuation_delay_se"][ok])
    return float(np.sqrt(np.mean(e**2))), float(np.sqrt(np.mean(r**2))), 1 - ok.mean(), cover


@pytest.fixture(scope="module")
def clean_table(tmp_path_factory: pytest.TempPathFactory) -> Any:
    p = tmp_path_factory.mktemp("ind") / "clean.h5"
    return extract_recording(write_independent_sweep(p, "ur10", N, Conditions(), seed=3),
                             progress=False).table  # fmt: skip


@pytest.fixture(scope="module")
def clean(clean_table: Any) -> tuple[float, float, float, float]:
    return _score(clean_table)


def test_response_error_is_neither_hidden_nor_inflated(clean_table: Any) -> None:
    """Clean: the response delay's standard error matches its error (RMS ratio 0.7-1.5;
    measured 1.1 on 300 trials, 0.040 / 0.036 ms; 1.08 on these 48). Taking the residual variance as
    independent noise gave 3.6 (0.133 / 0.037 ms: 100 % coverage) — each package's
    latency jitter enters two increments with opposite signs; 48 trials put ~10 % of
    sampling error on each RMS."""
    t = clean_table
    ok = np.array([not f for f in t["flag"]])
    err = (t["response_delay"] - t["true_response_delay"])[ok]
    se = t["response_delay_se"][ok]
    ratio = np.sqrt(np.mean(se**2)) / np.sqrt(np.mean(err**2))
    assert 0.7 <= ratio <= 1.5, ratio


def test_clean_independent_recording(clean: tuple[float, float, float, float]) -> None:
    """Clean: actuation and response RMSE <= 0.15 ms (measured ~0.12 / 0.05 ms on 300
    trials; 48 trials add ~10 % sampling error), nothing flagged."""
    act, resp, flagged, _ = clean
    assert act <= 0.15e-3
    assert resp <= 0.15e-3
    assert flagged == 0


def test_lossy_usb_stream_is_rebuilt_not_discarded(
    tmp_path: Path, clean: tuple[float, float, float, float]
) -> None:
    """2 % lost and 0.5 % duplicated USB blocks (every trial touched; the old extractor
    flagged all of them): <= 5 % flagged, RMSE within 0.05 ms of the clean sweep."""
    p = write_independent_sweep(tmp_path / "lossy.h5", "ur10", N,
                                Conditions(block_loss=0.02, block_dup=0.005), seed=3)  # fmt: skip
    act, resp, flagged, _ = _score(extract_recording(p, progress=False).table)
    assert flagged <= 0.05
    assert act <= clean[0] + 0.05e-3
    assert resp <= clean[1] + 0.05e-3


def test_noise_grows_the_error_smoothly_and_honestly(tmp_path: Path) -> None:
    """5x noise: the error stays below 0.8 ms (measured 0.54 ms on 300 trials, old 0.66)
    and the 95 % intervals cover the truth on >= 80 % of trials (measured 92 %; 48 trials
    give a binomial sd of 4 %)."""
    p = write_independent_sweep(tmp_path / "n5.h5", "ur10", N, Conditions(noise_factor=5), seed=3)
    act, _, flagged, cover = _score(extract_recording(p, progress=False).table)
    assert act <= 0.8e-3
    assert flagged <= 0.05
    assert cover >= 0.8


def test_response_at_10x_noise_is_accurate_and_its_error_honest(tmp_path: Path) -> None:
    """10x noise: the response delay's RMSE <= 0.25 ms and its 95 % intervals cover the
    truth on >= 90 % of trials (measured on 300 trials 0.153 ms and 98 %; before the gyro
    rate was averaged over 12 ms in the response fit 0.298 ms and 78 %, which fails both;
    48 trials add ~10 % sampling error to the RMSE, a binomial sd of ~2 % to the coverage).
    At least 90 % of the trials kept: the actuation's ``uncertain`` flag takes 4.7 % at 10x
    on 300 trials (48 trials: a binomial sd of 3 %)."""
    p = write_independent_sweep(tmp_path / "n10.h5", "ur10", N, Conditions(noise_factor=10),
                                seed=3)  # fmt: skip
    t = extract_recording(p, progress=False).table
    ok = np.array([not f for f in t["flag"]])
    r = (t["response_delay"] - t["true_response_delay"])[ok]
    assert ok.mean() >= 0.9
    assert np.sqrt(np.mean(r**2)) <= 0.25e-3
    assert np.mean(np.abs(r) <= 1.96 * t["response_delay_se"][ok]) >= 0.9


def test_held_up_state_packages_are_dated_by_the_controllers_stamps(tmp_path: Path) -> None:
    """A stall in 30 % of the trials (3-20 ms, anywhere in the trial) holds up the state
    packages due then, delivered in a burst when it ends. Dated by arrival the response fit
    read those trials up to 1.41 ms off, 7.5 standard errors (81 % coverage; on 300 trials
    per arm 3.2 / 3.0 / 2.6 ms on the UR10 / KR 5 / UR10e). With the generator's own
    controller stamps (another origin, a clock 60 ppm slow) the error is the clean one:
    measured RMSE 0.012 ms, at most 0.027 ms (0.016 / 0.018 / 0.017 ms on 300)."""
    out = {}
    for stamps in (False, True):
        cond = Conditions(held_up=0.3, controller_stamps=stamps)
        p = write_independent_sweep(tmp_path / f"held{stamps}.h5", "ur10", N, cond, seed=3)
        t = extract_recording(p, progress=False).table
        ok = np.array([not f for f in t["flag"]])
        out[stamps] = ((t["response_delay"] - t["true_response_delay"])[ok],
                       t["response_delay_se"][ok])  # fmt: skip
    err, _ = out[True]
    # 0.05 ms: the clean recording's RMSE with stamps on 300 trials is 0.016 ms.
    assert np.sqrt(np.mean(err**2)) < 5e-5
    assert np.max(np.abs(err)) < 1e-4
    bad, bad_se = out[False]
    assert np.max(np.abs(bad) / bad_se) > 4  # what dating by arrival gave: a hidden error


def test_relative_counter_rows_drops_duplicates_and_keeps_gaps() -> None:
    """Duplicated and backward frames dropped, a lone corrupted counter dropped, a wrap
    and a gap kept with their positions."""
    c = np.array([[65534, 65535, 0, 1, 2, 3], [5, 6, 7, 6, 7, 8], [1, 2, 9, 4, 5, 6],
                  [1, 2, 5, 6, 7, 8]], np.uint16)  # fmt: skip
    pos, keep = relative_counter_rows(c)
    assert pos[0].tolist() == [0, 1, 2, 3, 4, 5]
    assert keep[0].all()
    assert keep[1].tolist() == [True, True, True, False, False, True]
    assert keep[2].tolist() == [True, True, False, True, True, True]
    assert pos[3].tolist() == [0, 1, 4, 5, 6, 7]
    assert keep[3].all()


def test_drifting_clock_follows_a_rate_change() -> None:
    """Arrivals of a clock whose rate drifts by 300 ppm over 6 minutes (exponential warm-up)
    with 0-0.3 ms jitter, in 60 s windows (>= 31 groups each): blended curved envelopes
    stay within the 0.2 ms target (95th percentile; measured 0.09 ms), blended straight
    lines of the same length do not (measured 0.66 ms: the offset bends within a window
    while the rate keeps drifting), one line for the sweep errs by 12 ms."""
    rng = np.random.default_rng(0)
    t = np.linspace(0, 360, 4000)
    ppm = 300 * (1 - np.exp(-3 * t / 360)) / (1 - np.exp(-3))
    # sample index of the sensor at host time t: integrate the rate
    n = np.round(8000 * (t + 1e-6 * np.cumsum(ppm) * (t[1] - t[0]))).astype(np.int64)
    arrival = t + 5e-4 + rng.gamma(2, 1e-4, t.size)
    group = np.arange(t.size) // 13  # "trials" of 13 blocks

    def p95(fit: Any) -> float:
        err = fit.to_host_time(n) - 5e-4 - t  # the envelope is the minimum latency
        return float(np.percentile(np.abs(err), 95))

    curved = fit_clock_drifting(n, arrival, group, nominal_rate_hz=8000.0)
    lines = fit_clock_drifting(n, arrival, group, nominal_rate_hz=8000.0, curved=False)
    line = fit_clock_lower_envelope(n, arrival, nominal_rate_hz=8000.0)
    assert p95(curved) < 0.2e-3
    assert p95(lines) > 3 * p95(curved)
    assert p95(line) > 5 * p95(lines)
    assert curved.drift_ppm > 150
    assert curved.to_dict()["curved"] is True


def _transfer_stamps(
    read_period_s: float | None, seed: int = 4
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Block stamps of 120 trials (0.7 s each, 1 s apart, 3000 ppm fast) from a device that
    sends transfers of 8 samples ending at indices = 5 (mod 8); each trial records blocks
    of 8 from a random first sample, stamped with the arrival of the transfer that
    delivered the block's last row (gamma jitter over 0.7 ms), or, with
    ``read_period_s``, with the time of the first periodic read after that arrival.
    Returns (row index, stamp, trial, true host time of each stamp's row)."""
    rng = np.random.default_rng(seed)
    rate = 8000.0 * (1 + 3000e-6)
    ns, ts, gs, truth = [], [], [], []
    for trial in range(120):
        first = int(trial * rate) + int(rng.integers(0, 8))
        rows = first + np.arange(7, 5600, 8)  # each recorded block's last row
        end = rows + (5 - rows) % 8  # the transfer that delivered it ends there
        arrival = end / rate + 7e-4 + rng.gamma(2.0, 1.5e-4, rows.size)
        if read_period_s is not None:
            arrival = np.ceil(arrival / read_period_s) * read_period_s
        ns.append(rows)
        ts.append(arrival)
        gs.append(np.full(rows.size, trial))
        truth.append(rows / rate)
    return tuple(np.concatenate(x) for x in (ns, ts, gs, truth))  # type: ignore[return-value]


def test_clock_finds_the_devices_transfer_phase() -> None:
    """Fixed transfers of 8 samples, recorded blocks starting anywhere: one trial in eight
    reaches the minimum latency, the others' stamps are late by 1-7 samples. Searching the
    transfer phase dates every sample within 20 µs (measured 1.4 µs: the jitter's lowest
    values); taken as they are the curves bulge between the touching trials (99th
    percentile 0.41 ms here; up to 0.31 ms on the independent recordings).
    A recorder whose periodic reads (every 20 ms) do not follow the transfers shows no
    phase: none is claimed, the fit is the one without the search."""
    n, t, g, truth = _transfer_stamps(None)
    found = fit_clock_drifting(n, t, g, nominal_rate_hz=8000.0, transfer_samples=8)
    plain = fit_clock_drifting(n, t, g, nominal_rate_hz=8000.0)
    assert found.transfer_phase == 5
    assert plain.transfer_phase == -1
    err_found = np.abs(found.to_host_time(n) - 7e-4 - truth)
    err_plain = np.abs(plain.to_host_time(n) - 7e-4 - truth)
    assert np.percentile(err_found, 99) < 20e-6, np.percentile(err_found, 99)
    assert np.percentile(err_plain, 99) > 60e-6, np.percentile(err_plain, 99)

    n, t, g, _ = _transfer_stamps(0.02)
    reads = fit_clock_drifting(n, t, g, nominal_rate_hz=8000.0, transfer_samples=8)
    assert reads.transfer_phase == -1
    same = fit_clock_drifting(n, t, g, nominal_rate_hz=8000.0)
    assert np.array_equal(reads.to_host_time(n), same.to_host_time(n))


def test_gain_is_time_matched_on_a_slow_joint(tmp_path: Path) -> None:
    """KR 5 of the independent generator (12 Hz velocity loop: the joint still creeps in the
    pause): the gyro gain compares the angle with the position sampled when it ends, so the
    actuation bias stays within ±0.08 ms (measured on 300 trials +0.043 ms, RMSE 0.161 ms;
    reading the position a fixed 30 ms later scaled the speed ~1 % high: +0.122 ms, RMSE
    0.200 ms; on this seed's 96 trials +0.061 vs +0.139; the mean of 96 has a sd of ~0.016
    ms, so the bound sits ~1.2 sd above the new figure and ~3.7 sd below the old one)."""
    p = write_independent_sweep(tmp_path / "kr5.h5", "kr5", 96, Conditions(), seed=5)
    t = extract_recording(p, progress=False).table
    ok = np.array([not f for f in t["flag"]])
    e = (t["actuation_delay"] - t["true_actuation_delay"])[ok]
    assert ok.mean() >= 0.95
    assert abs(float(np.mean(e))) <= 0.08e-3, np.mean(e)


def test_ladder_cap_stops_a_group_before_its_biased_window() -> None:
    """Six windows whose estimates scatter like nested fits (sd 0.20 -> 0.12 ms) and whose
    widest is biased by +0.12 ms (a KR 5's, measured): one trial's Lepski test cannot see
    a bias of one standard deviation, the group's median step can — the cap is the fifth
    window (on 98 of 100 seeds; the sixth on the others). At 10x the noise (sd_0 2 ms,
    beyond LEPSKI_NOISE_SCALE_S) no cap: the narrow windows are no longer the unbiased
    ones there. Trials in no group (-1) neither get a cap nor count: 40 wild ones do not
    move the group's."""
    rng = np.random.default_rng(3)
    sd = np.array([0.20, 0.18, 0.15, 0.13, 0.125, 0.12]) * 1e-3
    bias = np.array([0, 0, 0, 0, 0, 0.12]) * 1e-3

    def ladder(n: int, scale: float) -> tuple[np.ndarray, np.ndarray]:
        # nested least squares: each wider estimate = the next narrower one + independent
        # noise of the variance difference
        t = np.empty((6, n))
        t[5] = rng.normal(0, sd[5] * scale, n)
        for j in range(4, -1, -1):
            t[j] = t[j + 1] + rng.normal(0, np.sqrt(sd[j] ** 2 - sd[j + 1] ** 2) * scale, n)
        return t + bias[:, None], np.repeat(sd[:, None] * scale, n, axis=1)

    t, s = ladder(40, 1.0)
    assert set(ladder_cap(t, s, np.zeros(40, np.int64)).tolist()) == {4}
    assert set(ladder_cap(t, s, None).tolist()) == {4}
    t_noisy, s_noisy = ladder(40, 10.0)
    assert set(ladder_cap(t_noisy, s_noisy, np.zeros(40, np.int64)).tolist()) == {5}
    wild = np.concatenate([t, rng.normal(0, 5e-3, (6, 40))], axis=1)
    groups = np.r_[np.zeros(40, np.int64), np.full(40, -1)]
    cap = ladder_cap(wild, np.concatenate([s, s], axis=1), groups)
    assert set(cap[:40].tolist()) == {4}
    assert set(cap[40:].tolist()) == {5}
