"""The bird's-eye page in headless Debian chromium (driven over the DevTools pipe, see ``cdp.py``).

- every track is drawn at its world position in its state's colour (pixels checked in a screenshot, at
  positions computed here from the page's documented view contract, not from the page's own code);
- hovering a box shows that track's z-scores;
- a new user changes alpha from the page (the token prompt included) and the borderline track turns from
  static to dynamic on screen.

Skips cleanly when chromium is not installed (CI: ``apt-get install -y chromium``).
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from .cdp import Chromium, find_chromium
from .stack import PAPER_STATISTIC, Stack, start_stack, wait_for

CHROMIUM = find_chromium()
pytestmark = [pytest.mark.integration,
              pytest.mark.skipif(CHROMIUM is None, reason="chromium not installed (apt-get install -y chromium)")]

TOKEN = "page-token"
VIEW = (-40.0, -25.0, 40.0, 25.0)
WIDTH, HEIGHT = 1280, 800
COLOURS = {"static": (0x3B, 0x82, 0xF6), "dynamic": (0xEF, 0x44, 0x44), "undecided": (0x9C, 0xA3, 0xAF)}
BACKGROUND = (0x0F, 0x14, 0x1A)


@pytest.fixture(scope="module")
def page_stack() -> Iterator[Stack]:
    s = start_stack("sc-page", token=TOKEN)
    yield s
    s.close()


@pytest.fixture(scope="module")
def browser() -> Iterator[Chromium]:
    assert CHROMIUM is not None
    b = Chromium(CHROMIUM, WIDTH, HEIGHT)
    yield b
    b.close()


@pytest.fixture
def shots(tmp_path: Path) -> Path:
    """Where screenshots go: the test's tmp dir, or ``$JG_SCREENSHOT_DIR`` to keep them for a look."""
    keep = os.environ.get("JG_SCREENSHOT_DIR")
    if keep:
        Path(keep).mkdir(parents=True, exist_ok=True)
        return Path(keep)
    return tmp_path


def _frozen_state(stack: Stack) -> dict:
    """Pause the feed and return the classifier's last state once the sidecar serves it unchanged."""
    stack.feeder.pause()
    last: dict[str, int] = {}

    def settled() -> dict | None:
        with stack.http() as c:
            body = c.get("/v1/state").json()
        same = last.get("seq") == body["seq"]
        last["seq"] = body["seq"]
        return body if same else None
    return wait_for(settled, "the state to settle with the feed paused", period=0.3)


def _to_px(rect: dict, x: float, y: float) -> tuple[float, float]:
    """The page's documented view contract (see the comment at the top of index.html)."""
    x0, y0, x1, y1 = VIEW
    cw, ch = rect["width"], rect["height"]
    s = min(cw / (x1 - x0), ch / (y1 - y0))
    return (rect["left"] + (cw - s * (x1 - x0)) / 2 + (x - x0) * s,
            rect["top"] + (ch - s * (y1 - y0)) / 2 + (y1 - y) * s)


def _colour_at(img: np.ndarray, px: float, py: float) -> tuple[int, int, int]:
    """Median colour of the 3×3 pixels around (px, py)."""
    x, y = int(round(px)), int(round(py))
    patch = img[y - 1:y + 2, x - 1:x + 2].reshape(-1, 3)
    return tuple(int(v) for v in np.median(patch, axis=0))  # type: ignore[return-value]


def _close(c: tuple[int, int, int], ref: tuple[int, int, int], tol: int = 14) -> bool:
    return all(abs(a - b) <= tol for a, b in zip(c, ref))


def _open(browser: Chromium, stack: Stack, seq: int | None = None) -> dict:
    browser.navigate(f"{stack.url}/?view={','.join(f'{v:g}' for v in VIEW)}&refresh=100")
    cond = f"window.jg.drawnSeq === {seq}" if seq is not None else "window.jg.drawnSeq >= 0"
    browser.wait_js(f"window.jg && {cond}")
    return browser.eval("(() => { const r = document.getElementById('view').getBoundingClientRect();"
                        " return {left: r.left, top: r.top, width: r.width, height: r.height}; })()")


def test_tracks_are_drawn_where_they_are_in_their_state_colour(page_stack: Stack, browser: Chromium,
                                                               shots: Path) -> None:
    try:
        state = _frozen_state(page_stack)
        rect = _open(browser, page_stack, state["seq"])
        img = browser.screenshot()
        browser.screenshot_png(str(shots / "page_tracks.png"))
    finally:
        page_stack.feeder.resume()
    assert img.shape == (HEIGHT, WIDTH, 3)
    states = {t["state"] for t in state["tracks"]}
    assert {"static", "dynamic"} <= states
    for t in state["tracks"]:
        px, py = _to_px(rect, t["x"], t["y"])
        assert rect["left"] < px < rect["left"] + rect["width"] and rect["top"] < py < rect["top"] + rect["height"]
        got = _colour_at(img, px, py)
        assert _close(got, COLOURS[t["state"]]), (t["class"], t["state"], (px, py), got)
    # Empty world is background (not a box, not a grid line): no stray drawing.
    px, py = _to_px(rect, 35.5, -22.5)
    assert _close(_colour_at(img, px, py), BACKGROUND, tol=6)
    # The header counts agree with the state.
    for key in ("static", "dynamic", "undecided"):
        assert browser.eval(f"document.getElementById('n-{key}').textContent") == str(state["counts"][key])
    assert "ready" in browser.eval("document.getElementById('ready').textContent")


def test_hover_shows_the_z_scores(page_stack: Stack, browser: Chromium) -> None:
    creeper = page_stack.track("creeper").track_id
    try:
        state = _frozen_state(page_stack)
        rect = _open(browser, page_stack, state["seq"])
        t = next(t for t in state["tracks"] if t["id"] == creeper)
        browser.mouse("mouseMoved", *_to_px(rect, t["x"], t["y"]))
        browser.wait_js("document.getElementById('tip').style.display === 'block'")
        tip = browser.eval("document.getElementById('tip').innerText")
        tip_id = browser.eval("document.getElementById('tip').dataset.track")
        zs = browser.eval("document.querySelector('#tip .zs').textContent")
    finally:
        page_stack.feeder.resume()
    assert tip_id == creeper
    assert zs == f"{t['z_x']:.2f} / {t['z_y']:.2f}"
    assert "static" in tip and f"{t['alpha']:.2f}" in tip and "10 / 10" in tip


def test_change_alpha_from_the_page_flips_the_borderline_track(page_stack: Stack, browser: Chromium,
                                                               shots: Path) -> None:
    creeper = page_stack.track("creeper").track_id
    page_stack.wait_state(lambda b: any(t["id"] == creeper and t["state"] == "static" for t in b["tracks"]),
                          "creeper static at the default alpha")
    _open(browser, page_stack)
    browser.wait_js("document.getElementById('f-alpha_default').value === '1.96'")
    try:
        browser.type_into("#f-alpha_default", "0.5")
        browser.click_element("#apply")
        # This sidecar has JG_API_TOKEN set: the page asks for it, the user types it and applies again.
        browser.wait_js("document.getElementById('token-row').style.display === 'block'")
        assert page_stack.classifier.core.config.alpha_default == 1.96  # the 401 applied nothing
        browser.type_into("#token", TOKEN)
        browser.click_element("#apply")
        browser.wait_js("document.getElementById('msg').textContent.startsWith('Applied')")
        assert page_stack.classifier.core.config.alpha_default == 0.5
        browser.wait_js(f"window.jg.state.tracks.some(t => t.id === '{creeper}' && t.state === 'dynamic')")
        # The change log (fed by /v1/events) tells the user what just happened.
        log = browser.wait_js("document.getElementById('log').innerText.includes('static → dynamic') &&"
                              " document.getElementById('log').innerText")
        assert "config changed" in log and creeper[:6] in log
        state = _frozen_state(page_stack)
        rect = _open(browser, page_stack, state["seq"])
        img = browser.screenshot()
        browser.screenshot_png(str(shots / "page_after_alpha.png"))
        t = next(t for t in state["tracks"] if t["id"] == creeper)
        assert t["state"] == "dynamic"
        assert _close(_colour_at(img, *_to_px(rect, t["x"], t["y"])), COLOURS["dynamic"])
    finally:
        page_stack.feeder.resume()
        with page_stack.http() as c:
            c.put("/v1/config", json=PAPER_STATISTIC)


def test_the_form_shows_the_config_in_force_with_every_value_a_choice_can_take(page_stack: Stack,
                                                                                  browser: Chromium) -> None:
    """The form's choices offer every value the config takes: ``effective_n`` had offered ``cluster`` and
    ``independent`` only, so under the default (``measured``) the page showed an empty choice, and once a user had
    picked another the page could not set the default back."""
    from typing import get_args

    from jitterguard.schemas.models import MAX_WINDOW, ClassifierConfig

    try:
        with page_stack.http() as c:
            assert c.patch("/v1/config", json={"effective_n": None}).json()["effective_n"] == "measured"
        _open(browser, page_stack)
        browser.wait_js("window.jg.config && window.jg.config.effective_n === 'measured'")
        for name in ("effective_n", "mode"):
            options = browser.eval(f"[...document.getElementById('f-{name}').options].map(o => o.value)")
            assert sorted(options) == sorted(get_args(ClassifierConfig.model_fields[name].annotation)), name
        assert browser.eval("document.getElementById('f-effective_n').value") == "measured"
        for name in ("window_size", "min_window"):  # the model's bounds, not ten times them
            assert browser.eval(f"document.getElementById('f-{name}').max") == str(MAX_WINDOW)
    finally:
        with page_stack.http() as c:
            c.put("/v1/config", json=PAPER_STATISTIC)


def test_chromium_is_found_when_installed() -> None:
    assert CHROMIUM == (shutil.which("chromium") or shutil.which("chromium-browser"))
