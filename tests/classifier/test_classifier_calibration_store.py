"""The online calibration survives the classifier's restart: the estimator's state round-trips exactly, a store
that cannot be used is ignored with a reason, the evidence taken over is capped, and a real service writes its
calibration when it stops and a new one starts from it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from jitterguard.runtime import loopback_options
from jitterguard.schemas import decode, encode, keys
from jitterguard.schemas.models import ClassifierConfig, TrackedObjects
from jitterguard.services.classifier.calibration import OnlineCalibration
from jitterguard.services.classifier.calibration_store import FORMAT, RESTORE_MAX_BLOCKS, CalibrationStore
from jitterguard.services.classifier.core import MotionClassifierCore, Observations
from jitterguard.services.classifier.service import ClassifierService
from jitterguard.services.classifier.synthetic_tracks import TrackScenario, generate

from helpers import wait_until


def _learnt(frames: int = 60, tracks: int = 40, seed: int = 3) -> MotionClassifierCore:
    """A core that has learnt from parked objects whose error is 3× what they report (σ 0.3 m vs 0.1 m)."""
    rng = np.random.default_rng(seed)
    core = MotionClassifierCore(ClassifierConfig(window_size=10))  # a block every 10 frames per track
    xy = rng.uniform(-35.0, 35.0, (tracks, 2))
    ids = [f"{i:032x}" for i in range(tracks)]
    for f in range(frames):
        p = xy + rng.normal(0.0, 0.3, xy.shape)
        core.update(Observations.from_lists(ids, [1] * tracks, p[:, 0], p[:, 1], [0.01] * tracks, [0.0] * tracks,
                                            [0.01] * tracks, stamp_ns=f * 100_000_000, seq=f))
        core.learn()
    return core


def test_a_state_restored_elsewhere_gives_the_same_model() -> None:
    online = _learnt().online_calibration
    fitted = online.refit()
    assert fitted.scale[0, :, 0, 0].min() > 4.0  # it learnt the 9× variance (the prior is 1)
    other = OnlineCalibration()
    assert other.restore(online.state()) == pytest.approx(online.effective_blocks)
    np.testing.assert_allclose(other.current.scale, fitted.scale, rtol=1e-12)
    np.testing.assert_allclose(other.current.tau_s, fitted.tau_s, rtol=1e-12)
    assert other.counts == online.counts


def test_the_evidence_taken_over_is_capped() -> None:
    online = _learnt().online_calibration
    assert online.effective_blocks > 100
    capped = OnlineCalibration()
    assert capped.restore(online.state(), max_blocks=50.0) == 50.0
    assert capped.effective_blocks == pytest.approx(50.0)
    full, cut = online.refit().scale[0, :, 0, 0], capped.current.scale[0, :, 0, 0]
    assert np.all((cut > 1.0) & (cut <= full * 1.000001))  # still learnt, pulled a little towards the prior


@pytest.mark.parametrize(("edit", "needle"), [
    (lambda s: s.update(band_edges_m=np.array([10.0, 30.0])), "range bands"),
    (lambda s: s.update(Y=s["Y"][..., :-1]), "'Y' has shape"),
    (lambda s: s.update(n=np.full_like(s["n"], np.nan)), "non-finite"),
    (lambda s: s.update(tau_grid_s=s["tau_grid_s"] * 2), "correlation times"),
    (lambda s: s.pop("het"), "missing 'het'"),
])
def test_a_state_that_does_not_fit_is_refused_and_changes_nothing(edit, needle) -> None:
    state = _learnt(frames=25, tracks=10).online_calibration.state()
    edit(state)
    fresh = OnlineCalibration()
    with pytest.raises(ValueError, match=needle):
        fresh.restore(state)
    assert fresh.effective_blocks == 0 and np.all(fresh.current.scale == 1.0)


def test_the_store_round_trips_and_explains_what_it_ignores(tmp_path: Path) -> None:
    store = CalibrationStore(tmp_path / "cal.npz")
    fresh = OnlineCalibration()
    assert "no stored calibration" in store.load_into(fresh)
    online = _learnt().online_calibration
    store.save(online.state())
    assert [p.name for p in tmp_path.iterdir()] == ["cal.npz"]  # no temp file left behind
    with np.load(store.path, allow_pickle=False) as z:  # plain arrays, readable without jitterguard
        assert str(z["format"]) == FORMAT and z["Et"].shape[-1] == 12
    why = store.load_into(fresh)
    assert why.startswith("calibration restored") and f"{RESTORE_MAX_BLOCKS:.0f} effective blocks" in why
    (tmp_path / "junk.npz").write_bytes(b"not a zip file")
    assert "unreadable" in CalibrationStore(tmp_path / "junk.npz").load_into(OnlineCalibration())
    np.savez(tmp_path / "other.npz", format=np.asarray("something/else"))
    assert "not a jitterguard.classifier-calibration/1 file" in CalibrationStore(tmp_path / "other.npz").load_into(
        OnlineCalibration())
    banded = OnlineCalibration(band_edges_m=(15.0,))
    assert "does not fit" in store.load_into(banded) and banded.effective_blocks == 0


@pytest.mark.parametrize("damage", ["truncated", "flipped byte", "an .npy file"])
def test_a_damaged_store_starts_cold_instead_of_crashing(tmp_path: Path, damage: str) -> None:
    """A torn copy (BadZipFile), a flipped byte (a CRC error on reading an array) or an .npy under the store's
    name (np.load returns an array, no context manager) had raised from the classifier's constructor, so
    supervisord restarted it into the same crash and no object was ever published."""
    store = CalibrationStore(tmp_path / "cal.npz")
    store.save(_learnt(frames=25, tracks=10).online_calibration.state())
    data = bytearray(store.path.read_bytes())
    if damage == "truncated":
        store.path.write_bytes(bytes(data[: len(data) // 2]))
    elif damage == "flipped byte":
        data[len(data) // 3] ^= 0xFF
        store.path.write_bytes(bytes(data))
    else:
        np.save(store.path.open("wb"), np.zeros(3))
    fresh = OnlineCalibration()
    why = store.load_into(fresh)
    assert "starting cold" in why and fresh.effective_blocks == 0


@pytest.mark.integration
def test_a_restarted_classifier_goes_on_calibrated(tmp_path: Path, zenoh_port, client_session) -> None:
    """A real service learns from 30 frames, writes its calibration as it stops; the next one starts with the
    same pooled evidence (and model) instead of the prior."""
    store = CalibrationStore(tmp_path / "run" / "classifier-calibration.npz")
    opts = loopback_options("cal", zenoh_port, listen_self=True)
    got: list[TrackedObjects] = []
    client_session.declare_subscriber(keys.objects("cal"), lambda s: got.append(decode(TrackedObjects,
                                                                                        s.payload.to_bytes())))
    frames = list(generate(TrackScenario(n_static=8, n_moving=0, n_starting=0, seed=4), 30))
    with ClassifierService(opts, ClassifierConfig(), straggler_timeout_s=0.5, calibration_store=store) as first:
        assert first.core.online_calibration.effective_blocks == 0  # nothing stored yet: a cold start
        assert wait_until(lambda: any(True for _ in client_session.liveliness().get(keys.alive("cal", "classifier"),
                                                                                      timeout=0.5)), 10)
        for f in frames:
            n = len(got)
            for o in f.observations:
                client_session.put(keys.track("cal", o.track.object_id), encode(o))
            client_session.put(keys.tracked("cal"), encode(f.tracked))
            assert wait_until(lambda: len(got) == n + 1, timeout=30)
    learnt = first.core.online_calibration
    assert learnt.effective_blocks > 0 and first.counters.get("calibration_saves") >= 1
    assert store.path.is_file()
    with ClassifierService(opts, ClassifierConfig(), calibration_store=store) as second:
        restored = second.core.online_calibration
        assert restored.effective_blocks == pytest.approx(min(learnt.effective_blocks, RESTORE_MAX_BLOCKS))
        np.testing.assert_allclose(second.core.noise_model().scale, learnt.refit().scale, rtol=1e-12)
        assert second.core.calibration_state()["effective_blocks"] > 0
