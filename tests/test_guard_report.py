"""The guard command's printed report (gac_jax.cli.guard.print_report): the count of criteria
within their margins is the count of rows the rule decided within, however many undecided
rows the report shows (it shows the first few of them)."""

from __future__ import annotations

from gac_jax.cli import guard


def _row(status: str, kind: str = "recall") -> dict:
    iv = [-0.1, 0.1] if status == "within" else [-0.3, 0.7] if status == "undecided" else [0.6, 0.9]
    row = {"kind": kind, "status": status, "diff": 0.2, "margin": 0.5}
    row |= {"within_interval": iv, "beyond_interval": iv}
    if kind == "ap":
        return row | {"se": 0.1}
    return row | {"ref_only": 3, "cand_only": 5, "n": 1000}


def _report(statuses: dict[str, int]) -> dict:
    rows, i = {}, 0
    for status, count in statuses.items():
        for _ in range(count):
            rows[f"Car easy crit{i}"] = _row(status, "ap" if i % 4 == 3 else "recall")
            i += 1
    spread = {"median": 0.0, "p95": 0.0, "max": 0.0}
    matched = {"matched": 10, "reference_detections": 10, "detections": 10}
    matched |= {k: spread for k in ("score", "centre_m", "dimensions_m", "heading_deg")}
    matched |= {"heading_flips": 0, "heading_flip_share": 0.0}
    decision = {"look": 1, "alpha_look": 0.025, "criteria": rows}
    decision |= {"verdict": "undecided", "reason": "too few frames"}
    cand = {"decision": decision, "ap": {"Car 3d@0.70 easy": 10.0}, "matched": matched}
    return {
        "frames": 4000,
        "reference_ap": {"Car 3d@0.70 easy": 10.0},
        "candidates": {"openvino:int8": cand | {"model_ms": 16.0}},
        "guard_file": "guard.json",
    }


def test_within_count_is_the_rows_decided_within(capsys):
    shown = guard.SHOWN_UNDECIDED
    guard.print_report(_report({"within": 7, "undecided": shown + 12, "beyond": 2}), 40.0)
    out = capsys.readouterr().out
    total = 7 + shown + 12 + 2
    assert f"7 of {total} criteria within their margins" in out
    assert "... and 12 more undecided" in out


def test_all_within_says_so(capsys):
    guard.print_report(_report({"within": 9}), None)
    out = capsys.readouterr().out
    assert "9 of 9 criteria within their margins\n" in out
