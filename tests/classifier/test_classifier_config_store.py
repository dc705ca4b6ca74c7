"""The classifier's config survives its restart: ConfigStore on disk (read back with plain ``json``, a second
reader), and the service storing a write before applying it and restoring it at start."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from jitterguard.runtime import loopback_options
from jitterguard.schemas import decode, encode, keys
from jitterguard.schemas.models import ClassifierConfig, ConfigReply
from jitterguard.services.classifier.config_store import FORMAT, ConfigStore
from jitterguard.services.classifier.config_writes import ConfigWritePolicy
from jitterguard.services.classifier.service import ClassifierService

from helpers import wait_until

FLAGS = ClassifierConfig(window_size=12)
SET = ClassifierConfig(window_size=12, alpha_default=2.5, alpha_per_class={"car": 3.0}, mode="chi2")


def test_save_then_load_and_the_file_as_plain_json(tmp_path: Path) -> None:
    store = ConfigStore(tmp_path / "classifier-config.json")
    assert store.load(FLAGS)[0] is None
    store.save(FLAGS, SET)
    doc = json.loads((tmp_path / "classifier-config.json").read_text())
    assert doc["format"] == FORMAT and doc["config"]["alpha_default"] == 2.5 and doc["config"]["mode"] == "chi2"
    assert doc["started_with"]["window_size"] == 12 and doc["config"]["alpha_per_class"] == {"car": 3.0}
    assert store.load(FLAGS) == (SET, f"config restored from {store.path}")
    assert [p.name for p in tmp_path.iterdir()] == ["classifier-config.json"]  # no temp file left behind


def test_changed_flags_win_over_the_stored_config(tmp_path: Path) -> None:
    store = ConfigStore(tmp_path / "c.json")
    store.save(FLAGS, SET)
    config, why = store.load(ClassifierConfig(window_size=14))
    assert config is None and "flags changed" in why


@pytest.mark.parametrize("text", ["{not json", "[]", json.dumps({"format": "other"}),
                                  json.dumps({"format": FORMAT, "started_with": {}, "config": {"window_size": 1}})])
def test_unreadable_or_invalid_files_are_ignored_with_a_reason(tmp_path: Path, text: str) -> None:
    (tmp_path / "c.json").write_text(text)
    store = ConfigStore(tmp_path / "c.json")
    config, why = store.load(ClassifierConfig())
    assert config is None and "starting from the flags" in why and store.damaged


@pytest.mark.integration
def test_a_damaged_store_is_a_warning_and_counted_not_the_info_of_a_first_start(tmp_path, zenoh_port,
                                                                                caplog) -> None:
    """A store the classifier cannot read loses every write it held. That had been logged at INFO, as a first start
    or changed flags are, and counted nowhere: the stack's status, /metrics and the run summary all looked fine while
    the thresholds an operator had set were gone. Now a warning naming the file, and ``config_store_errors``."""
    import logging

    store = ConfigStore(tmp_path / "classifier-config.json")
    store.save(FLAGS, SET)
    store.path.write_text(store.path.read_text()[:60])  # cut short, as a full disk or a hand edit leaves it
    opts = loopback_options("cs3", zenoh_port, listen_self=True)
    with caplog.at_level(logging.INFO, logger="jitterguard"), ClassifierService(opts, FLAGS, config_store=store) as svc:
        assert svc.core.config == FLAGS and svc.counters.get("config_store_errors") == 1
    warned = [r for r in caplog.records if r.levelno == logging.WARNING and str(store.path) in r.getMessage()]
    assert warned and "unreadable" in warned[0].getMessage()
    store.path.unlink()  # no file: a first start, which is no error
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="jitterguard"), ClassifierService(opts, FLAGS, config_store=store) as svc:
        assert svc.counters.get("config_store_errors") == 0
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING and str(store.path) in r.getMessage()]


def _write(session, payload: bytes):
    return [r for r in session.get(keys.classifier_config("cs"), payload=payload, timeout=5.0)][0]


@pytest.mark.integration
def test_a_write_survives_the_classifiers_restart_and_an_unstorable_write_is_refused(tmp_path, zenoh_port,
                                                                                   client_session) -> None:
    store = ConfigStore(tmp_path / "run" / "classifier-config.json")
    opts = loopback_options("cs", zenoh_port, listen_self=True)
    with ClassifierService(opts, FLAGS, config_store=store, config_writes=ConfigWritePolicy.open()) as svc:
        assert wait_until(lambda: any(True for _ in client_session.liveliness().get(keys.alive("cs", "classifier"),
                                                                                      timeout=0.5)), 10)
        reply = decode(ConfigReply, _write(client_session, encode(SET)).ok.payload.to_bytes())
        assert reply.ok and svc.core.config == SET
    assert json.loads(store.path.read_text())["config"]["alpha_default"] == 2.5
    with ClassifierService(opts, FLAGS, config_store=store) as svc:  # restarted with the same flags
        assert svc.core.config == SET
    with ClassifierService(opts, ClassifierConfig(window_size=20), config_store=store) as svc:  # new flags
        assert svc.core.config == ClassifierConfig(window_size=20)
    blocked = ConfigStore(tmp_path / "run" / "classifier-config.json" / "inside-a-file.json")
    with ClassifierService(opts, FLAGS, config_store=blocked, config_writes=ConfigWritePolicy.open()) as svc:
        assert wait_until(lambda: any(True for _ in client_session.liveliness().get(keys.alive("cs", "classifier"),
                                                                                      timeout=0.5)), 10)
        err = _write(client_session, encode(SET)).err
        assert err is not None
        refused = decode(ConfigReply, err.payload.to_bytes())
        assert not refused.ok and "not applied" in refused.error and "cannot store" in refused.error
        # counted twice: the load at start (a path under a file cannot be read either) and the write
        assert svc.core.config == FLAGS and svc.counters.get("config_store_errors") == 2


@pytest.mark.integration
def test_a_restored_config_uses_its_own_calibration_file_and_survives_losing_it(tmp_path, zenoh_port) -> None:
    """Started with --calibration-file A, a write switched to file B and was stored. After a restart with the same
    flags the config said B while the scales were A's (the CLI reads the flags' file, the service only read one
    when none was given); and once B was gone, every start raised from the constructor."""
    from jitterguard.services.classifier.calibration import NoiseModel
    from jitterguard.services.classifier.calibration_file import read_calibration, write_calibration

    def file_with_scale(name: str, k: float) -> Path:
        prior = NoiseModel.prior()
        model = NoiseModel(prior.band_edges_m, prior.scale * k, prior.correlation, prior.tau_s, prior.blocks,
                           prior.frame_interval_s, prior.track_dof)
        write_calibration(tmp_path / name, model, window=20)
        return tmp_path / name

    a, b = file_with_scale("a.yaml", 2.0), file_with_scale("b.yaml", 5.0)
    flags = ClassifierConfig(calibration="file", calibration_file=str(a))
    store = ConfigStore(tmp_path / "run" / "classifier-config.json")
    store.save(flags, flags.model_copy(update={"calibration_file": str(b), "alpha_default": 3.33}))
    opts = loopback_options("cs2", zenoh_port, listen_self=True)
    with ClassifierService(opts, flags, config_store=store, calibration_model=read_calibration(a)) as svc:
        assert svc.core.config.calibration_file == str(b)
        assert svc.core.noise_model().scale.max() == pytest.approx(5.0)
    b.rename(tmp_path / "b.moved")
    # the file is gone: the flags' calibration source, every other write kept (the threshold had been dropped with
    # it, and nothing counted), and the store holds what is in force ...
    in_force = flags.model_copy(update={"alpha_default": 3.33})
    with ClassifierService(opts, flags, config_store=store, calibration_model=read_calibration(a)) as svc:
        assert svc.core.config == in_force and svc.core.noise_model().scale.max() == pytest.approx(2.0)
        assert svc.counters.get("config_store_errors") == 1
    assert ConfigStore(store.path).load(flags)[0] == in_force
    # ... so the file coming back does not bring back at the next restart a config that was not in force
    (tmp_path / "b.moved").rename(b)
    with ClassifierService(opts, flags, config_store=store, calibration_model=read_calibration(a)) as svc:
        assert svc.core.config == in_force and svc.counters.get("config_store_errors") == 0


@pytest.mark.parametrize(("value", "token"), [("", None), (" \t\n", None), (" s3cret\n", "s3cret"), ("s3cret", "s3cret")])
def test_the_token_is_read_once_the_same_way_for_classifier_and_sidecar(monkeypatch, value, token) -> None:
    """A blank JG_API_TOKEN had been a token (the sidecar then bound 0.0.0.0 behind a secret no request could
    carry); the whitespace an env file leaves around one cannot travel in a bearer header either."""
    from jitterguard.services.sidecar.app import SidecarSettings
    monkeypatch.setenv("JG_API_TOKEN", value)
    assert ConfigWritePolicy.from_env().token == token
    assert SidecarSettings.token_from_env() == token
