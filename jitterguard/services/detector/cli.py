"""CLI of the detector area: ``jitterguard detector`` and ``jitterguard bench detector``."""

from __future__ import annotations

import json
import os
from typing import Annotated

import typer

from ...cli_common import (ConnectOpt, ListenOpt, LogLevelOpt, NsOpt, ProgressOpt, ZenohConfigOpt, fail, progress_on,
                           zenoh_options)
from .config import PRESETS

WeightsOpt = Annotated[
    str | None,
    typer.Option("--weights", help="Weights file (torch.save dict, loaded weights_only). Default: the shipped"
                 " weights of --preset; without them a randomly initialised network (logged loudly)."),
]
PresetOpt = Annotated[str, typer.Option("--preset", help=f"Architecture preset: {', '.join(PRESETS)}.")]
BackendOpt = Annotated[str, typer.Option("--backend", help="What runs the network: torch or onnxruntime.")]
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


def _parse_presets(text: str) -> tuple[str, ...]:
    names = tuple(s.strip() for s in text.split(",") if s.strip())
    unknown = [n for n in names if n not in PRESETS]
    if not names or unknown:
        fail(f"--presets: expected comma-separated names from {', '.join(PRESETS)}, got {text!r}")
    return tuple(dict.fromkeys(names))


def register(app: typer.Typer, bench_app: typer.Typer) -> None:
    @app.command("detector")
    def detector_cmd(
        ns: NsOpt = "default",
        zenoh_config: ZenohConfigOpt = None,
        connect: ConnectOpt = None,
        listen: ListenOpt = None,
        weights: WeightsOpt = None,
        preset: PresetOpt = "lite",
        threads: ThreadsOpt = None,
        score_threshold: Annotated[
            float | None,
            typer.Option("--score-threshold", min=0.0, max=1.0,
                         help="Keep detections scoring above this (default: the weights' config)."),
        ] = None,
        twist: Annotated[
            bool, typer.Option("--twist/--no-twist", help="Publish the network's velocity as the twist.")
        ] = True,
        backend: BackendOpt = "torch",
        onnx_dir: OnnxDirOpt = None,
        log_level: LogLevelOpt = "INFO",
    ) -> None:
        """Run the detector: points in; one DetectedObjects per scan (sensor frame, with variances) out."""
        if preset not in PRESETS:
            fail(f"--preset: expected one of {', '.join(PRESETS)}, got {preset!r}")
        if weights is not None and not os.path.isfile(weights):
            fail(f"--weights: file not found: {weights}")
        if backend not in ("torch", "onnxruntime"):
            fail(f"--backend: expected torch or onnxruntime, got {backend!r}")
        if onnx_dir is not None and (backend != "onnxruntime" or weights is not None):
            fail("--onnx: goes with --backend onnxruntime and replaces --weights")
        if onnx_dir is not None and not os.path.isdir(onnx_dir):
            fail(f"--onnx: folder not found: {onnx_dir}")
        opts = zenoh_options(ns, zenoh_config, connect, listen)

        from ...runtime import setup_logging

        setup_logging(log_level)
        passive_openmp()
        from .inference import Detector, WeightsError
        from .service import DetectorService

        try:  # load before the session opens: a bad weights file fails before anything is on the network
            if backend == "onnxruntime":
                from .onnx_backend import open_onnx_detector

                det = open_onnx_detector(onnx_dir, weights, preset, threads=threads, score_threshold=score_threshold)
            else:
                det = Detector.load(weights, preset, threads=threads, score_threshold=score_threshold)
        except WeightsError as exc:
            fail(f"{'--onnx' if onnx_dir else '--weights'}: {_one_line(exc)}")
        try:
            service = DetectorService(opts, det, has_twist=twist)
        except ValueError as exc:  # build_config names the bad endpoint / setting
            fail(str(exc))
        service.run_forever()

    @bench_app.command("detector")
    def bench_detector_cmd(
        json_out: Annotated[bool, typer.Option("--json", help="Print the result as one JSON document.")] = False,
        presets: Annotated[str, typer.Option("--presets", help="Comma-separated presets to time.")] = "lite,paper",
        scans: Annotated[int, typer.Option("--scans", min=1, max=10_000, help="Timed scans per preset.")] = 40,
        warmup: Annotated[int, typer.Option("--warmup", min=0, max=1000, help="Untimed scans first.")] = 3,
        threads: ThreadsOpt = None,
        weights: Annotated[
            list[str] | None,
            typer.Option("--weights", help="PRESET=FILE: time these weights for PRESET (repeatable); default the"
                         " shipped weights, else random init (same cost)."),
        ] = None,
        scenario: Annotated[str, typer.Option("--scenario", help="Synthetic scenario the scans come from.")] = "mixed",
        seed: Annotated[int, typer.Option("--seed")] = 0,
        progress: ProgressOpt = None,
        backends: Annotated[
            str | None,
            typer.Option("--backends", help="torch or torch,onnxruntime (timed side by side in this process, scan"
                         " by scan). Default: both when onnxruntime is installed."),
        ] = None,
    ) -> None:
        """Time the detector end to end per HDL-32E scan (voxelisation, network, decode, NMS)."""
        progress = progress_on(progress)
        from .bench import SCENARIOS, available_backends, run

        chosen = available_backends() if backends is None else tuple(dict.fromkeys(
            b.strip() for b in backends.split(",") if b.strip()))
        if "torch" not in chosen or any(b not in ("torch", "onnxruntime") for b in chosen):
            fail(f"--backends: expected torch or torch,onnxruntime, got {backends!r}")
        if "onnxruntime" in chosen and "onnxruntime" not in available_backends():
            fail("--backends: onnxruntime needs the onnxruntime, onnx and onnxscript packages (pip install 'jitterguard[onnx]')")

        names = _parse_presets(presets)
        if scenario not in SCENARIOS:
            fail(f"--scenario: expected one of {', '.join(SCENARIOS)}, got {scenario!r}")
        files: dict[str, str] = {}
        for item in weights or []:
            name, sep, path = item.partition("=")
            if not sep or name not in PRESETS or not path:
                fail(f"--weights: expected PRESET=FILE with PRESET one of {', '.join(PRESETS)}, got {item!r}")
            if not os.path.isfile(path):
                fail(f"--weights: file not found: {path}")
            files[name] = path
        passive_openmp()
        from .inference import WeightsError

        try:
            result = run(names, scans=scans, warmup=warmup, threads=threads, weights=files, scenario=scenario,
                         seed=seed, progress=progress, backends=chosen)
        except WeightsError as exc:
            fail(f"--weights: {_one_line(exc)}")
        if json_out:
            typer.echo(json.dumps(result))
            return
        from rich.console import Console
        from rich.table import Table

        table = Table(title=f"detector end to end per scan ({result_threads(result)} threads)")
        for col in ("preset", "points", "p50 ms", "p99 ms", "voxelize", "network", "decode", "detections"):
            table.add_column(col, justify="right")
        for name, row in result.items():
            for label, r in ((name, row), (f"{name} (onnxruntime)", row.get("onnxruntime"))):
                if r is None:
                    continue
                st = r["stages_ms"]
                table.add_row(label, f"{r['points']:.0f}", f"{r['p50_ms']:.1f}", f"{r['p99_ms']:.1f}",
                              f"{st['voxelize']:.1f}", f"{st['network']:.1f}", f"{st['decode']:.1f}",
                              f"{r['detections']:.0f}")
        Console().print(table)


def result_threads(result: dict) -> str:
    return ",".join(sorted({str(r["threads"]) for r in result.values()}))
