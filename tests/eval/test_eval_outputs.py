"""What ``jitterguard eval`` hands an engineer: report.md says what metrics.json holds, metrics.json's ``run`` block
is enough to run the same evaluation again, and a run that could score nothing is refused before it starts."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from jitterguard.cli import main

LATENCIES = (("time_to_first_correct_s_median_z", "never_correct_fraction_z"),
             ("time_to_first_correct_s_median_speed", "never_correct_fraction_speed"),
             ("time_to_dynamic_s_median_z", "never_dynamic_fraction_z"),
             ("time_to_dynamic_s_median_speed", "never_dynamic_fraction_speed"))


def _eval(argv: list[str], capsys: pytest.CaptureFixture[str]) -> dict:
    with pytest.raises(SystemExit) as exc:
        main(["eval", *argv, "--json"])
    assert exc.value.code == 0
    return json.loads(capsys.readouterr().out)


def test_report_latencies_show_the_pairs_that_never_got_there(tmp_path: Path, capsys) -> None:
    """A median time to a decision is over the pairs that reached it: report.md gives, beside it, the share that
    never did, as metrics.json holds it (it had shown 0.200 s for pedestrians 80 % of whom were never called
    dynamic on this run)."""
    out = tmp_path / "ev"
    m = _eval(["--scenario", "parking-street", "--seed", "0", "--duration", "5", "--out", str(out)], capsys)
    rows = {line.split("|")[1].strip(): [c.strip() for c in line.split("|")[1:-1]]
            for line in (out / "report.md").read_text().split("\n## ")[0].splitlines() if line.startswith("| ")}
    seen_never = 0
    for g, block in m["motion"].items():
        cells = rows[g][-4:]  # the four latency columns, in LATENCIES' order
        for cell, (time_key, never_key) in zip(cells, LATENCIES):
            t, never = block[time_key], block[never_key]
            assert cell.startswith("—" if t is None else f"{t:.3f}"), (g, time_key, cell)
            if never:
                seen_never += 1
                shown = re.search(r"\((\d+|< 1) % never\)", cell)
                assert shown, (g, never_key, cell)
                if shown.group(1) != "< 1":
                    assert int(shown.group(1)) == round(100 * never), (g, never_key, cell)
            else:
                assert "never" not in cell, (g, never_key, cell)
    assert seen_never  # the run has pairs that never got there (pedestrians: most of them)
    assert m["motion"]["pedestrian"]["never_dynamic_fraction_z"] > 0.5

