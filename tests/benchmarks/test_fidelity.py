"""benchmarks/fidelity.py's agreement rule: rates agree within two standard errors of their difference plus 0.02,
and the no-op outcome must be the same; per set and size, the share of levels that agree."""

from benchmarks.fidelity import compare, summarize


def counts(success: int, failure: int, episodes: int = 100) -> dict:
    return {"success": success, "failure": failure, "timeout": episodes - success - failure, "unstable": 0}


def level(noop: str, success: int, failure: int) -> dict:
    return {"noop": noop, "random": counts(success, failure)}


def test_equal_rates_agree_and_far_rates_do_not():
    ours = {"hand/s/a": level("timeout", 50, 10), "hand/s/b": level("timeout", 62, 0)}
    theirs = {"hand/s/a": level("timeout", 50, 10), "hand/s/b": level("timeout", 6, 0)}
    report = compare(ours, theirs)
    assert report["hand/s/a"]["agree"]
    assert not report["hand/s/b"]["agree"]
    assert not report["hand/s/b"]["random_success"]["agree"] and report["hand/s/b"]["random_failure"]["agree"]
    # 0.62 against 0.06 over 100 episodes each: standard error sqrt(.62 .38 / 100 + .06 .94 / 100) = 0.0540.
    assert abs(report["hand/s/b"]["random_success"]["standard_error"] - 0.05404) < 1e-4


def test_the_threshold_is_two_standard_errors_plus_two_points():
    # 0.30 against 0.20 over 100 episodes: standard error 0.0608, threshold 0.1416 > 0.10: agree;
    # 0.35 against 0.20: 0.15 > 2 x 0.0622 + 0.02 = 0.1445: disagree.
    report = compare(
        {"r/s/near": level("timeout", 30, 0), "r/s/far": level("timeout", 35, 0)},
        {"r/s/near": level("timeout", 20, 0), "r/s/far": level("timeout", 20, 0)},
    )
    assert report["r/s/near"]["agree"] and not report["r/s/far"]["agree"]


def test_a_different_noop_outcome_disagrees_and_shares_are_per_set_and_size():
    same = {"hand/s/b": level("timeout", 0, 0), "hand/m/c": level("failure", 0, 0)}
    ours = {"hand/s/a": level("success", 0, 0), **same}
    theirs = {"hand/s/a": level("timeout", 0, 0), **same}
    summary = summarize(compare(ours, theirs))
    assert summary["hand/s"] == {"levels": 2, "agree": 1, "disagree": ["hand/s/a"], "share": 0.5}
    assert summary["hand/m"]["share"] == 1.0
