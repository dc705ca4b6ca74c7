"""The report's figures show every curve and no empty panel (read back as images with Pillow)."""

from __future__ import annotations

import numpy as np
from PIL import Image

from jitterguard.eval.pipeline import Records
from jitterguard.eval.report import plot_alpha_sweep, plot_pr, plot_speed_vs_z


def records(groups: list[str], n: int = 40) -> Records:
    rng = np.random.default_rng(0)
    g = np.array([groups[i % len(groups)] for i in range(n)])
    dyn = np.arange(n) % 3 == 0
    z = np.where(dyn, 5.0, 0.5) + rng.normal(0, 0.1, n)
    return Records(t_s=np.arange(n) * 0.1, seq=np.arange(n), track_id=np.array([f"t{i % 7}" for i in range(n)]),
                   label=np.ones(n, np.int64), z=z, speed=np.where(dyn, 3.0, 0.1), window=np.full(n, 5),
                   state_z=np.ones(n, np.int8), state_v=np.ones(n, np.int8), gt_instance=np.arange(n),
                   gt_dynamic=dyn, group=g, alpha=np.full(n, 1.96), velocity_threshold=1.0, min_window=2)


def test_a_scene_without_cyclists_gets_no_bicycle_panel(tmp_path):
    for plot in (plot_pr, plot_speed_vs_z, plot_alpha_sweep):
        plot(records(["vehicle", "pedestrian"]), tmp_path / "two.png")
        plot(records(["vehicle", "pedestrian", "bicycle"]), tmp_path / "three.png")
        w2, w3 = Image.open(tmp_path / "two.png").width, Image.open(tmp_path / "three.png").width
        assert w2 * 3 == w3 * 2, (plot.__name__, w2, w3)


def test_coinciding_pr_curves_both_stay_visible(tmp_path):
    """Both scores separate the classes perfectly, so both curves lie on precision 1: the z-test's wide line
    shows between the dashes of the speed rule drawn over it."""
    plot_pr(records(["vehicle"]), tmp_path / "pr.png")
    img = np.asarray(Image.open(tmp_path / "pr.png").convert("RGB")).astype(int)

    def has(rgb: tuple[int, int, int]) -> bool:
        return bool((np.abs(img - np.array(rgb)).sum(axis=2) < 60).sum() > 50)

    assert has((31, 119, 180))  # tab:blue, the z-test line
    assert has((255, 127, 14))  # tab:orange, the speed line (dashed, on top)


def test_the_figures_name_the_test_that_scored(tmp_path):
    """In chi2 mode the records' z is the χ² test's p as a normal score: the axis and the PR legend say so (they
    had read ``z = max(z_x, z_y)`` and ``z-test`` whatever the mode). Drawn as SVG, whose text comments name every
    label."""
    rec = records(["vehicle"])
    for mode, want, never in (("z_test", ("z = max(z_x, z_y)", "z-test (AP"), "χ²"),
                              ("chi2", ("z of the χ² test", "χ² test (AP"), "max(z_x, z_y)")):
        plot_speed_vs_z(rec, tmp_path / f"{mode}-z.svg", mode)
        plot_pr(rec, tmp_path / f"{mode}-pr.svg", mode)
        text = (tmp_path / f"{mode}-z.svg").read_text() + (tmp_path / f"{mode}-pr.svg").read_text()
        for w in want:
            assert w in text, (mode, w)
        assert never not in text, mode


def _calibration(scale: float, blocks: float) -> dict:
    bands = {"0-20": scale, "20-40": scale, "40-inf": scale}
    axis = {"scale": bands, "scale_young": bands, "blocks": dict.fromkeys(bands, blocks),
            "blocks_young": dict.fromkeys(bands, blocks), "correlation": 0.5}
    return {"groups": {"vehicle": {"along": axis, "across": axis, "track_dof": 10.0}}}


def test_the_calibration_figure_names_its_bars_and_keeps_them_in_view(tmp_path):
    """The bars are named by axis, range band in metres and track age in words (they had read ``al 0-20 y``), and
    a run too short to learn any scale (every one 1, no blocks) keeps its bars below the top of the axes, their
    block counts clear of the title (the log axis had collapsed onto 1, every bar reaching the top)."""
    from jitterguard.eval.report import plot_calibration

    assert plot_calibration(_calibration(1.0, 0.0), tmp_path / "cal.svg")
    text = (tmp_path / "cal.svg").read_text()
    for label in ("along 0-20 m", "across 40-inf m young"):
        assert label in text, label
    assert plot_calibration(_calibration(1.0, 0.0), tmp_path / "cal.png")
    img = np.asarray(Image.open(tmp_path / "cal.png").convert("RGB")).astype(int)
    orange = (np.abs(img - np.array([255, 127, 14])).sum(axis=2) < 40).any(axis=1)
    frame = ((img.sum(axis=2) < 150).sum(axis=1) > img.shape[1] * 0.3)  # the axes' top and bottom edges
    top_edge = int(np.flatnonzero(frame)[0])
    assert int(np.flatnonzero(orange)[0]) > top_edge + 20  # the bars end well below the axes' top


_WRITE_FAILS_MIDWAY = """
import resource, signal, sys
sys.path.insert(0, sys.argv[2])
from test_eval_plots import records
from jitterguard.eval.report import plot_pr

plot_pr(records(["vehicle"]), sys.argv[1] + ".warm.png")  # imports, fonts and caches before the limit
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails (EFBIG) instead of killing us
resource.setrlimit(resource.RLIMIT_FSIZE, (4096, resource.getrlimit(resource.RLIMIT_FSIZE)[1]))
try:
    plot_pr(records(["vehicle", "pedestrian"]), sys.argv[1])
except OSError:
    sys.exit(3)
"""


def test_a_figure_whose_write_fails_midway_leaves_the_earlier_picture_whole(tmp_path):
    """A figure written over an earlier one, the disk refusing the write after 4 KiB (a file-size limit: as good
    as a full disk, and real even for root): the write fails and the earlier PNG is there byte for byte, with no
    temporary file beside it. ``savefig`` onto the path had truncated the old picture first and left 4 KiB of
    the new one."""
    import subprocess
    import sys
    from pathlib import Path

    out = tmp_path / "pr.png"
    plot_pr(records(["vehicle"]), out)
    before = out.read_bytes()
    assert len(before) > 4096
    done = subprocess.run([sys.executable, "-c", _WRITE_FAILS_MIDWAY, str(out), str(Path(__file__).parent)],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 3, done.stderr  # the write did fail (OSError), and said so
    assert out.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["pr.png", "pr.png.warm.png"]


def test_every_figure_of_the_package_is_saved_through_save_figure():
    """No module of the package calls ``.savefig(`` but :mod:`jitterguard.files` (whose ``save_figure`` renders
    into memory and renames a whole file into place): an AST walk, so a comment or docstring naming it is no hit."""
    import ast
    from pathlib import Path

    import jitterguard

    root = Path(jitterguard.__file__).parent
    direct = []
    for py in sorted(root.rglob("*.py")):
        if py == root / "files.py":
            continue
        for node in ast.walk(ast.parse(py.read_text(), filename=str(py))):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "savefig":
                direct.append(f"{py.relative_to(root)}:{node.lineno}")
    assert not direct, direct
