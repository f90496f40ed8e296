"""The equal-time benchmark: time-to-error interpolation and ratios on synthetic curves, the claims, and a tiny
smoke run (32x32, 0.5 s, two methods) of ``segmitsuba bench equal-time``."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from segmitsuba import benchmarks
from segmitsuba.benchmarks.equal_time import (
    CLAIMS,
    Ratio,
    SceneResult,
    evaluate_claims,
    mean_curve,
    running_min,
    time_to_error,
    time_to_error_ratio,
)

TIMES = [0.25 * 2**k for k in range(8)]  # 0.25 .. 32 s, doubling as the passes of compare.run_method


def power_law(c: float, slope: float, times=TIMES) -> list[float]:
    return [c * t**slope for t in times]


@pytest.mark.parametrize("slope", [-1.0, -0.5, -2.0])
@pytest.mark.parametrize("target", [0.3, 0.05, 0.011])
def test_time_to_error_is_exact_on_power_laws(slope, target):
    """Log-log interpolation is exact on e = c t^slope, between checkpoints too."""
    c = 0.2
    t = time_to_error(TIMES, power_law(c, slope), target)
    expected = (target / c) ** (1 / slope)
    if expected < TIMES[0]:
        assert t == TIMES[0]  # already there at the first checkpoint: its time, an upper bound
    elif expected > TIMES[-1]:
        assert t is None
    else:
        assert t == pytest.approx(expected, rel=1e-12)


def test_ratio_of_power_laws():
    """M: e = a/t, P: e = b/t. P reaches its final error b/T at T; M reaches it at aT/b: ratio b/a. With
    different slopes the ratio is the exact crossing of the two laws."""
    a, b, T = 0.01, 0.04, TIMES[-1]
    r = time_to_error_ratio(TIMES, power_law(a, -1), TIMES, power_law(b, -1))
    assert r.value == pytest.approx(b / a) and r.peer_time == pytest.approx(T) and not r.lower_bound
    assert r.target == pytest.approx(b / T) and r.time == pytest.approx(a * T / b)
    assert str(r) == "4"
    # M slower than P (3x the error at every time): it never reaches P's final error within the same budget
    assert str(time_to_error_ratio(TIMES, power_law(3 * b, -1), TIMES, power_law(b, -1))) == "never"
    # a steeper M that starts worse: e = 0.16 t^-2 crosses b/T = 1.25e-3 at sqrt(0.16 / 1.25e-3) = 11.3 s
    r = time_to_error_ratio(TIMES, power_law(0.16, -2), TIMES, power_law(b, -1))
    assert r.time == pytest.approx(math.sqrt(0.16 / (b / T))) and r.value == pytest.approx(T / r.time)
    # M = sqrt-law: e = 0.02 t^-0.5 reaches b/T = 1.25e-3 at (0.02/1.25e-3)^2 = 256 s: never within T
    assert time_to_error_ratio(TIMES, power_law(0.02, -0.5), TIMES, power_law(b, -1)).value is None
    # a method against itself: 1
    assert time_to_error_ratio(TIMES, power_law(b, -1), TIMES, power_law(b, -1)).value == pytest.approx(1)


def test_a_curve_that_never_gets_there():
    flat = [0.1, 0.09, 0.085, 0.083, 0.082, 0.0815, 0.0812, 0.081]
    assert time_to_error(TIMES, flat, 0.08) is None
    r = time_to_error_ratio(TIMES, flat, TIMES, power_law(0.04, -1))
    assert r.value is None and r.time is None and str(r) == "never"


def test_non_monotone_noise_uses_the_running_minimum():
    """A firefly raises the error after a good checkpoint: the running minimum keeps the progress, the first
    crossing counts, and the interpolation starts from the best error so far (not the spike)."""
    errors = [1.0, 0.5, 0.8, 0.2, 0.6, 0.1]
    t = [1.0, 2.0, 4.0, 8.0, 16.0, 32.0]
    assert running_min(errors).tolist() == [1.0, 0.5, 0.5, 0.2, 0.2, 0.1]
    # 0.6 is first reached between t=1 (1.0) and t=2 (0.5); the spike to 0.8 and 0.6 later do not matter
    expected = math.exp(math.log(1) + (math.log(0.6) - math.log(1.0)) / (math.log(0.5) - math.log(1.0)) * math.log(2))
    assert time_to_error(t, errors, 0.6) == pytest.approx(expected)
    # 0.3: between t=4 (best so far 0.5, not the spike's 0.8) and t=8 (0.2)
    f = (math.log(0.3) - math.log(0.5)) / (math.log(0.2) - math.log(0.5))
    assert time_to_error(t, errors, 0.3) == pytest.approx(math.exp(math.log(4) + f * (math.log(8) - math.log(4))))
    assert time_to_error(t, errors, 0.2) == pytest.approx(8.0)  # exactly at a checkpoint
    # a peer whose own final error was beaten earlier reaches it before the end: T_P(e_P) < T
    peer = [0.5, 0.05, 0.3, 0.2, 0.15, 0.1]
    r = time_to_error_ratio(t, errors, t, peer)
    assert r.peer_time < 2.0 and r.time == pytest.approx(32.0) and r.value < 1 / 16


def test_already_below_at_the_first_checkpoint_is_a_lower_bound():
    r = time_to_error_ratio(TIMES, power_law(1e-4, -1), TIMES, power_law(0.04, -1))
    assert r.lower_bound and r.time == TIMES[0] and str(r).startswith(">")
    assert r.value == pytest.approx(TIMES[-1] / TIMES[0])


def test_bad_input_is_refused():
    with pytest.raises(ValueError, match="times"):
        time_to_error([1, 2], [0.1], 0.05)
    with pytest.raises(ValueError, match="> 0"):
        time_to_error([1, 2], [0.1, 0.05], 0.0)
    assert isinstance(Ratio(0.1, 1.0, None, False).value, type(None))


def test_method_specs_carry_properties():
    from segmitsuba.benchmarks.equal_time import parse_method, split_methods

    assert parse_method("path") == ("path", {})
    spec = " segment_bdf[glossy_vertices=filtered, kernel_scale=12, direct_samples=2, hide_emitters=true]"
    assert parse_method(spec) == ("segment_bdf", {"glossy_vertices": "filtered", "kernel_scale": 12,
                                                  "direct_samples": 2, "hide_emitters": True})
    assert parse_method("segment_bdf[alpha=0.5]")[1] == {"alpha": 0.5}
    assert split_methods("path, segment_bdf[a=1,b=2],segment_pf") == ["path", "segment_bdf[a=1,b=2]", "segment_pf"]
    for bad in ("segment_bdf[kernel]", "segment_bdf[=3]", "segment bdf", "segment_bdf[a=1"):
        with pytest.raises(ValueError, match="method"):
            parse_method(bad)


def test_mean_curve_averages_runs_at_common_times():
    """Power laws are exact under log-log interpolation, so at every grid time the mean curve is the mean of
    the laws; one run is returned unchanged; ratios and final errors of a SceneResult use the seeds' mean."""
    times_b = [0.3 * 2**k for k in range(7)]  # another seed's checkpoints fall elsewhere
    t, e = mean_curve([(TIMES, power_law(0.01, -1)), (times_b, power_law(0.03, -1, times_b))], points=9)
    assert t[0] == pytest.approx(times_b[0]) and t[-1] == pytest.approx(times_b[-1]) and len(t) == 9
    assert np.allclose(e, [0.02 / x for x in t], rtol=1e-9)
    assert mean_curve([(TIMES, power_law(0.01, -1))]) == (TIMES, power_law(0.01, -1))
    with pytest.raises(ValueError):
        mean_curve([])

    class Run:  # the fields of compare.MethodRun that SceneResult reads
        def __init__(self, method, times, errors):
            self.method = method
            self.checkpoints = [type("C", (), {"time": a, "relmse": b})() for a, b in zip(times, errors, strict=True)]

    a = [Run("m", TIMES, power_law(0.01, -1)), Run("m", TIMES, power_law(0.03, -1))]
    p = [Run("p", TIMES, power_law(0.08, -1))]
    result = SceneResult("s", 32, TIMES[-1], {}, runs=[a[0], p[0]], seed_runs={"m": a})
    assert result.final_errors()["m"] == pytest.approx(0.02 / TIMES[-1]) and result.spread("m") == pytest.approx(3)
    # the mean law 0.02/t reaches the peer's 0.08/T at T/4: ratio 4 (the first seed alone would give 8)
    assert result.ratios("p")["m"].value == pytest.approx(4.0, rel=1e-6)


def test_claims_pass_and_fail():
    good = {
        "caustic": {"segment_mvf": 0.3, "segment_pf": 0.02, "segment_bdf": 0.021},
        "glossy_occluded": {"segment_mvf": 0.013, "segment_pf": 0.024, "segment_bdf": 0.012},
        "cornell": {"segment_mvf": 0.010, "segment_pf": 0.013, "segment_bdf": 0.0115},
    }
    claims = evaluate_claims(good)
    assert [c.scene for c in claims] == [s for s, _ in CLAIMS]
    assert all(c.passed for c in claims), [str(c) for c in claims]
    assert str(claims[0]).startswith("PASS  caustic:") and "mvf/pf 15.00" in str(claims[0])

    bad = json.loads(json.dumps(good))
    bad["caustic"]["segment_bdf"] = 0.023  # 1.15x pf: beyond the 1.1x allowed
    bad["glossy_occluded"]["segment_bdf"] = 0.0131  # not the best: mvf is
    bad["cornell"]["segment_bdf"] = 0.0125  # pf still the worst, but bdf 1.25x mvf
    assert [c.passed for c in evaluate_claims(bad)] == [False, False, False]
    bad["cornell"] = {"segment_mvf": 0.014, "segment_pf": 0.013, "segment_bdf": 0.0115}  # pf not the worst
    assert evaluate_claims(bad)[2].passed is False
    bad["caustic"] = {"segment_mvf": 0.028, "segment_pf": 0.02, "segment_bdf": 0.02}  # mvf only 1.4x pf
    assert evaluate_claims(bad)[0].passed is False

    partial = evaluate_claims({"caustic": {"segment_pf": 0.02}})
    assert [c.passed for c in partial] == [None, None, None] and str(partial[0]).startswith("SKIP")


def test_benchmark_name_maps_to_the_module():
    assert "equal-time" in benchmarks.available() and "equal_time" not in benchmarks.available()
    assert benchmarks.load("equal-time").__name__ == "segmitsuba.benchmarks.equal_time"
    assert benchmarks.load("equal_time") is benchmarks.load("equal-time")
    with pytest.raises(ValueError, match="unknown benchmark"):
        benchmarks.load("equal-times")


def test_smoke_run(tmp_path: Path):
    """32x32 against the stored test reference, 1 s each for path and segment_bdpt: the report, the PNG and
    the JSON with every checkpoint and the ratios (each method against itself is 1)."""
    out = tmp_path / "bench"
    report = benchmarks.run("equal-time", ["--res", "32", "--time", "1", "--scenes", "cornell", "--methods",
                                           "path,segment_bdpt", "--out", str(out), "-q", "--seeds", "2"])
    assert "[cornell] 32x32, max_depth 8, 1 s per method x 2 seeds" in report
    assert "SKIP  caustic" in report and "PASS" not in report and "FAIL" not in report
    assert (out / "error_vs_time_cornell.png").read_bytes()[:4] == b"\x89PNG"
    data = json.loads((out / "results.json").read_text())
    assert data["settings"]["time_budget"] == 1 and data["settings"]["res"] == 32
    cornell = data["scenes"]["cornell"]
    assert cornell["reference"]["integrator"] == "path"
    for method in ("path", "segment_bdpt"):
        run = cornell["methods"][method]
        checkpoints = run["checkpoints"]
        assert checkpoints and run["params"] == {"max_depth": 8}  # one pass at least (a loaded machine: maybe 1)
        assert np.all(np.diff([c["time"] for c in checkpoints]) > 0)
        assert checkpoints[-1]["relmse"] == pytest.approx(run["final"]["relmse"], rel=1e-6)
        (second,) = run["seeds"]  # the other seed's run, its own image
        assert second["checkpoints"] and second["final"]["relmse"] != run["final"]["relmse"]
        assert run["mean_final_relmse"] == pytest.approx((run["final"]["relmse"] + second["final"]["relmse"]) / 2)
        assert run["final"]["relmse"] > 0 and math.isfinite(run["final"]["relmse"])
        assert cornell["time_to_error_ratios"][method][method]["value"] == pytest.approx(1.0)
    line = next(x for x in report.splitlines() if x.strip().startswith("segment_bdpt"))
    assert len(line.split()) >= 8  # method, passes, spp, time, relMSE, its spread, two ratios
