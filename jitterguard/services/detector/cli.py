"""CLI of the detector area: ``jitterguard detector``.

Commands import their implementation when they run (start-up time: see :mod:`jitterguard.cli`).
"""

from __future__ import annotations

import os
from typing import Annotated

import typer

from ...cli_common import (ConnectOpt, ListenOpt, LogLevelOpt, NsOpt, ParamFileOpt, SensorHeightOpt, ZenohConfigOpt, fail,
                           SensorTiltOpt, float_option, sensor_height_option, sensor_tilt_option, zenoh_options)
from ...config import ConfigError, load
from .config import PRESETS, DetectorParams, declared_height, measures_tilt, params_refusal

WeightsOpt = Annotated[
    str | None,
    typer.Option("--weights", help="Weights file (torch.save dict, loaded weights_only). Default: the shipped"
                 " weights of --preset; without them a randomly initialised network (logged loudly)."),
]
PresetOpt = Annotated[str, typer.Option("--preset", help=f"Architecture preset: {', '.join(PRESETS)}.")]
BackendOpt = Annotated[str | None, typer.Option("--backend", help="What runs the network: torch or onnxruntime.")]
OnnxDirOpt = Annotated[
    str | None,
    typer.Option("--onnx", help="onnxruntime backend: a folder written by `jitterguard export-onnx`. Default: export"
                 " --weights / --preset at start-up into a temporary folder."),
]
ThreadsOpt = Annotated[
    int | None, typer.Option("--threads", min=1, max=1024, help="torch CPU threads (default: the machine's cores).")
]


def passive_openmp() -> None:
    """Make OpenMP's idle threads sleep instead of spinning, unless the user chose otherwise.

    Must run before torch is imported (libgomp reads it once). On cores shared with other work — the tracker,
    classifier and replay of the same stack, or anything else on the host — spinning workers steal the CPU the
    busy worker needs: measured on this project's 2-core machine beside a training run, the lite preset's p50
    went from 250–1500 ms (default policy) to 70–145 ms (passive) at 2 threads. Idle cores lose at most a few
    wake-ups' worth of latency.
    """
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def retain_heap() -> None:
    """Keep freed memory in the process instead of handing it back to the kernel after every step.

    Training allocates and frees the same multi-megabyte activation buffers every step; glibc serves them with
    mmap and returns them with munmap, so each step pays page faults on fresh zeroed pages. On this project's
    2-core VM a training run drifted into ~70 % system time and 4.4 s per step; with a 1 GiB mmap threshold
    and no trimming (plus passive OpenMP) the same run went at 0.39 s per step. A no-op where glibc's
    ``mallopt`` is not available.
    """
    import ctypes
    import ctypes.util

    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # not glibc
        return
    m_trim_threshold, m_top_pad, m_mmap_threshold = -1, -2, -3
    mallopt(m_mmap_threshold, 1 << 30)
    mallopt(m_trim_threshold, 1 << 31)
    mallopt(m_top_pad, 256 << 20)


def _one_line(exc: Exception, limit: int = 240) -> str:
    """An exception's message on one line (torch's load errors run to several paragraphs)."""
    msg = " ".join(str(exc).split())
    return msg if len(msg) <= limit else msg[: limit - 1] + "…"


def register(app: typer.Typer, bench_app: typer.Typer) -> None:
    @app.command("detector")
    def detector_cmd(
        ns: NsOpt = "default",
        zenoh_config: ZenohConfigOpt = None,
        connect: ConnectOpt = None,
        listen: ListenOpt = None,
        config: ParamFileOpt = None,
        weights: WeightsOpt = None,
        preset: Annotated[str | None, typer.Option(
            "--preset", help=f"Architecture preset: {', '.join(PRESETS)} (default lite).")] = None,
        threads: ThreadsOpt = None,
        score_threshold: Annotated[
            float | None,
            float_option("--score-threshold", min=0.0, max=1.0,
                         help="Keep detections scoring above this (default: the weights' config)."),
        ] = None,
        twist: Annotated[
            bool | None, typer.Option("--twist/--no-twist", help="Publish the network's velocity as the twist.")
        ] = None,
        backend: BackendOpt = None,
        onnx_dir: OnnxDirOpt = None,
        flips: Annotated[bool | None, typer.Option("--flips/--no-flips", help="Average the network over the scan"
                                                   " and its three mirror images (~4x the network's time).")
                         ] = None,
        sensor_height: SensorHeightOpt = None,
        sensor_tilt: SensorTiltOpt = None,
        log_level: LogLevelOpt = "INFO",
    ) -> None:
        """Run the detector: points in; one DetectedObjects per scan (sensor frame, with variances) out."""
        try:
            params = load(DetectorParams, config, overrides={
                "weights": weights, "preset": preset, "threads": threads, "score_threshold": score_threshold,
                "twist": twist, "backend": backend, "onnx": onnx_dir, "flips": flips,
                "sensor_height_m": sensor_height_option(sensor_height), "sensor_tilt": sensor_tilt_option(sensor_tilt)})
        except ConfigError as exc:
            fail(f"--config: {exc}" if config is not None else str(exc))
        refused = params_refusal(params)
        if refused is not None:  # named as the user gave it: the flag, or the file's key
            key, why = refused
            flagged = {"preset": preset, "weights": weights, "onnx": onnx_dir, "backend": backend}[key] is not None or config is None
            fail(f"--{key}: {why}" if flagged else f"--config: {config}: {key}: {why}")
        opts = zenoh_options(ns, zenoh_config, connect, listen)

        from ...runtime import setup_logging

        setup_logging(log_level)
        passive_openmp()
        from .inference import Detector, WeightsError
        from .service import DetectorService

        try:  # load before the session opens: a bad weights file fails before anything is on the network
            if params.backend == "onnxruntime":
                from .onnx_backend import open_onnx_detector

                det = open_onnx_detector(params.onnx, params.weights, params.preset, threads=params.threads,
                                         score_threshold=params.score_threshold, self_crop=params.self_crop,
                                         flips=params.flips, sensor_height_m=declared_height(params.sensor_height_m),
                                         sensor_tilt=measures_tilt(params.sensor_tilt))
            else:
                det = Detector.load(params.weights, params.preset, threads=params.threads,
                                    score_threshold=params.score_threshold, self_crop=params.self_crop,
                                    flips=params.flips, sensor_height_m=declared_height(params.sensor_height_m),
                                    sensor_tilt=measures_tilt(params.sensor_tilt))
        except WeightsError as exc:
            fail(f"{'--onnx' if params.onnx else '--weights'}: {_one_line(exc)}")
        except ValueError as exc:  # flips on weights whose grid is not symmetric about the sensor
            fail(f"--flips: {_one_line(exc)}")
        if params.weights or params.onnx:  # the file fixes the network: a --preset naming another one was ignored
            from .train_cli import check_preset

            check_preset(preset, params.weights or params.onnx, det.config.name)
        try:
            service = DetectorService(opts, det, has_twist=params.twist, sweeps=params.sweeps,
                                      max_sweep_lag_s=params.max_sweep_lag_s, max_scan_bytes=params.max_scan_bytes)
        except ValueError as exc:  # build_config names the bad endpoint / setting
            fail(str(exc))
        service.run_forever()

