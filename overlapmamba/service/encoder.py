"""The exported encoder, as onnxruntime runs it: range images in, descriptors out.

    images       (B, V, H, W) float32, the model's own projection (from its metadata):
                 V sub-column views of each scan (V = 1 for most models)
    descriptor   (B, D) float32, unit norm
    yaw_features (B, C, W) float32, rolled by the sensor's yaw

Nothing about the projection is configured here: :class:`EncoderMetadata` in the file says
which sensor profile the network was trained on, how other sensors' scans enter it and how
many views make a descriptor (:mod:`overlapmamba.core.views`), and :meth:`Encoder.project` uses
exactly them with the scan's sensor (:mod:`overlapmamba.service.sensors`). The graph itself
takes one image a row (B·V, 1, H, W); :meth:`Encoder.encode` combines the views.

**Two ways to run the same file.** The *portable* graph is the file as it is: onnxruntime
inlines each scan node's body (ONNX ``Scan`` loops). The *C-kernel* path
(:mod:`overlapmamba.service.fastscan`) cuts the graph at its scan nodes and runs each scan with the
kernel the model was trained with. It is built at load, then checked against the portable
graph on a fixed input (max abs difference ≤ :data:`PARITY_TOL` in both outputs), and timed
against it on one scan of that input (:func:`_time_both`): only when it agrees, and costs no
more than :data:`KERNEL_SLOWER` × the portable graph's CPU time on this machine, does it serve.
CPU time, not wall time: the service is sized by its load, where every core is busy and what
a scan costs all threads together bounds the throughput; and in blocks, not call by call,
because after a run the portable graph's onnxruntime workers spin on the cores for a while,
and a kernel call timed just after one ran beside them (that made the choice a coin flip on
one 2-core machine, where the kernel costs about half the portable graph's CPU a scan:
``python benchmarks/scan_choice.py``, reports/service/scan-choice.json).
Anything that fails (no kernel, a file exported before scans were marked, a
parity miss) is logged as a warning and the portable graph serves: :attr:`Encoder.scan_path`
says which one runs, and ``/readyz`` shows it.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import numpy as np
import onnxruntime as ort

from overlapmamba.core.modelmeta import INPUT, OUTPUTS, EncoderMetadata, check_identity
from overlapmamba.core.points import PointCloud
from overlapmamba.core.sensors.input import ALL_SCANS_MODES, SensorInput
from overlapmamba.core.views import combine_views, project_views_offset, unshift_features

if TYPE_CHECKING:
    from overlapmamba.service.fastscan import StagedGraph

log = logging.getLogger("overlapmamba.service")
PARITY_TOL = 1e-4  # max abs difference, C-kernel path vs portable graph, at load


class ModelLoadError(RuntimeError):
    """The model file is missing, unreadable, or not an OverlapMamba encoder."""


@dataclass(frozen=True)
class Encoded:
    descriptor: np.ndarray  # (D,) float32
    yaw_features: np.ndarray  # (C, W) float32


class Encoder:
    def __init__(
        self,
        path: Path,
        *,
        intra_op_threads: int = 0,
        scan_kernel: bool | Literal["auto"] = "auto",
    ) -> None:
        if not Path(path).is_file():
            raise ModelLoadError(f"model file {path} does not exist")
        opts = ort.SessionOptions()
        threads = intra_op_threads or (os.cpu_count() or 1)
        self.threads = threads  # onnxruntime's (and the scan kernel's) a call
        opts.intra_op_num_threads = threads
        opts.inter_op_num_threads = 1
        t0 = time.perf_counter()
        try:
            self.session = ort.InferenceSession(
                str(path), sess_options=opts, providers=["CPUExecutionProvider"]
            )
        except Exception as err:  # onnxruntime raises its own unrelated classes
            raise ModelLoadError(f"onnxruntime cannot load {path}: {err}") from None
        self.meta = check_graph(self.session, path)
        self.path = Path(path)
        self.staged: StagedGraph | None = None  # the C-kernel path, when it serves
        self.scan_path = "portable (scan_kernel = false)"
        if self.meta.network.get("mixer", "mamba") != "mamba":
            self.scan_path = f"no scan ({self.meta.network['mixer']} mixer)"
        elif scan_kernel:
            self.scan_path = self._try_scan_kernel(opts, threads, timed=scan_kernel == "auto")
        self.load_s = time.perf_counter() - t0
        if self.meta.weights != "trained":
            log.warning(
                "model %s has %s weights: its descriptors are not trained for place recognition",
                self.meta.model_id,
                self.meta.weights,
            )

    def _run_portable(self, images: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        desc, yaw = self.session.run(list(OUTPUTS), {INPUT: images})
        return desc, yaw

    def _try_scan_kernel(self, opts: ort.SessionOptions, threads: int, timed: bool) -> str:
        """Build the C-kernel path and serve with it if it agrees with the portable graph
        (and, ``timed``, is not slower here); otherwise say why (a warning) and keep the
        portable graph. Returns :attr:`scan_path`."""
        try:
            import onnx

            from overlapmamba.core.scan_kernel import load
            from overlapmamba.service.fastscan import FastPathError, StagedGraph

            load()
            staged = StagedGraph(onnx.load(str(self.path)), opts, threads)
            x = parity_image(self.meta)
            want = self._run_portable(x)
            got = staged.run(x)
            gap = max(float(np.abs(a - b).max()) for a, b in zip(got, want, strict=True))
            if not gap <= PARITY_TOL:  # NaN fails too
                raise FastPathError(
                    f"it disagrees with the portable graph by {gap:.3g} (allowed ≤ {PARITY_TOL})"
                )
        except Exception as err:  # onnxruntime's and onnx's own classes too: never fatal here
            log.warning(
                "model %s: the C scan kernel is not used, the portable graph serves (slower): %s",
                self.meta.model_id,
                err,
            )
            return f"portable ({err})"
        if not timed:
            self.staged = staged
            n, k = staged.scan_count, len(staged.stages)
            return f"c-kernel ({n} scans, {k} sessions; max abs {gap:.1e} vs the portable graph)"
        # The cheaper on the processors measured since the kernel flushes subnormals itself;
        # before, on one cloud Xeon it cost about 1.4–1.7 × the portable graph (the ring's
        # fast lanes went subnormal: reports/service/scan-subnormals.json). Kept as a guard.
        # Time both on one scan of the parity image (its views, as a scan is served; a
        # start-up costs a few tenths of a second more) and serve with the cheaper.
        scan = np.concatenate([x] * self.meta.descriptors_per_scan)
        kernel_ms, portable_ms = _time_both(
            lambda: staged.run(scan), lambda: self._run_portable(scan)
        )
        timing = f"{kernel_ms:.1f} against {portable_ms:.1f} ms of CPU a scan at load"
        if kernel_ms > KERNEL_SLOWER * portable_ms:
            log.warning(
                "model %s: the C scan kernel is slower than the portable graph on this machine "
                "(%s): the portable graph serves",
                self.meta.model_id,
                timing,
            )
            return f"portable (the C kernel was slower here: {timing})"
        self.staged = staged
        n, k = staged.scan_count, len(staged.stages)
        return (
            f"c-kernel ({n} scans, {k} sessions; max abs {gap:.1e} vs the portable graph; {timing})"
        )

    @property
    def model_id(self) -> str:
        return self.meta.model_id

    @property
    def dim(self) -> int:
        return self.meta.descriptor_dim

    @property
    def views(self) -> int:
        return self.meta.views

    def project(self, points: PointCloud, sensor: SensorInput | None = None) -> np.ndarray:
        """(V, H, W) float32 range images in the model's sensor profile, V = :attr:`views`;
        ``sensor``: the scan's sensor, projected as the model takes it (None: the model's
        own sensor). A file with aligned columns also needs each image's offset for its yaw
        features: :meth:`project_offset`."""
        return self.project_offset(points, sensor)[0]

    def project_offset(
        self, points: PointCloud, sensor: SensorInput | None = None
    ) -> tuple[np.ndarray, float]:
        """:meth:`project` and its column offset (:mod:`overlapmamba.core.views`; 0 unless the
        file aligns columns), which :meth:`encode` shifts the yaw features back by."""
        aligned = self.meta.aligned
        if sensor is None and self.meta.sensor_input in ALL_SCANS_MODES:
            sensor = self.own_input  # even the model's own scans are thinned
        if sensor is None:
            return project_views_offset(points, self.meta.profile, self.meta.views, aligned=aligned)
        return sensor.project_offset(points, self.meta.views, aligned=aligned)

    @cached_property
    def own_input(self) -> SensorInput:
        """The model's own sensor into its input (a plain projection unless the file takes
        every sensor's common beams, ``common`` or ``structure``, or a bird's-eye view, ``bev``)."""
        return SensorInput.own(self.meta.profile, self.meta.sensor_input)

    def encode(
        self, images: np.ndarray, offsets: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """images (B, V, H, W) → descriptor (B, D), yaw_features (B, C, W) in the sensor's
        columns. ``offsets`` (B,): the images' column offsets (:meth:`project_offset`), which
        the yaw features are shifted back by; a file with aligned columns needs them (its
        images' columns are not the sensor's), for the others None means 0."""
        if offsets is None and self.meta.aligned:
            raise ValueError(
                f"model {self.meta.model_id} aligns each scan's columns (column_phase aligned): "
                "pass the images' column offsets from Encoder.project_offset, so that the yaw "
                "features come back in the sensor's columns"
            )
        p = self.meta.profile
        want = (self.meta.views, p.height, p.width)
        if images.ndim != 4 or images.shape[1:] != want:
            raise ValueError(
                f"images must have shape (B, {', '.join(map(str, want))}) (B scans, "
                f"{self.meta.views} views each, from Encoder.project); got {images.shape}"
            )
        x = np.ascontiguousarray(images, dtype=np.float32).reshape(-1, 1, p.height, p.width)
        out = self.staged.run(x) if self.staged is not None else self._run_portable(x)
        desc, yaw = combine_views(*out, self.meta.descriptors_per_scan)
        return (desc, yaw) if offsets is None else (desc, unshift_features(yaw, offsets))

    def describe(
        self,
        clouds: Iterable[PointCloud],
        sensor: SensorInput | None = None,
        *,
        batch: int = 8,
        mapped: bool = True,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Scans of one sensor → (N, D) descriptors, (N, C, W) yaw features, ``batch`` scans
        a pass: projected, encoded and (``mapped``) taken into the model sensor's space as
        the service answers them. ``mapped=False``: the network's own descriptors (what
        sensor maps are fitted on)."""
        descs: list[np.ndarray] = []
        yaws: list[np.ndarray] = []
        chunk: list[PointCloud] = []

        def flush() -> None:
            projected = [self.project_offset(p, sensor) for p in chunk]
            d, y = self.encode(
                np.stack([im for im, _ in projected]), np.array([o for _, o in projected])
            )
            descs.append(self.to_model_space(d, sensor) if mapped else d)
            yaws.append(y)
            chunk.clear()

        for cloud in clouds:
            chunk.append(cloud)
            if len(chunk) == batch:
                flush()
        if chunk:
            flush()
        if not descs:
            raise ValueError("no scans to describe")
        return np.concatenate(descs), np.concatenate(yaws)

    def to_model_space(self, desc: np.ndarray, sensor: SensorInput | None) -> np.ndarray:
        """Descriptors (B, D) or (D,) of scans of ``sensor`` (from :meth:`encode`) as the
        service answers them: mapped into the model sensor's space where the file carries a
        map for that sensor (:mod:`overlapmamba.core.sensormaps`), else as they are."""
        sensor_map = None if sensor is None else self.meta.sensor_maps.get(sensor.sensor.name)
        return desc if sensor_map is None else sensor_map.apply(desc)


KERNEL_SLOWER = 1.1  # the kernel serves unless it costs more than this × the portable graph
TIMING_CALLS = 3  # timed calls of each path at load, after a warm one
TIMING_PAUSE_S = 0.02  # after a block: longer than onnxruntime's idle workers spin


def _time_both(kernel: Callable[[], object], portable: Callable[[], object]) -> tuple[float, float]:
    """CPU ms a call of each (the process's, every thread: what a busy machine pays), each
    timed in a block of its own (a warm call, then :data:`TIMING_CALLS` back to back), the
    kernel's first: the portable graph's workers, which spin after its runs, then spin after
    the timing, not into the kernel's."""
    spent = []
    for fn in (kernel, portable):
        fn()
        t = time.process_time()
        for _ in range(TIMING_CALLS):
            fn()
        spent.append(1e3 * (time.process_time() - t) / TIMING_CALLS)
        time.sleep(TIMING_PAUSE_S)
    return spent[0], spent[1]


def check_graph(session: ort.InferenceSession, path: Path | str) -> EncoderMetadata:
    """The metadata of an encoder's session, checked against itself and against what the
    graph does: its id against its identity fields, the graph's input and output names, and
    one run on two scans of the metadata's own input (a batch of them, float32, H × W of its
    profile) giving descriptors and yaw features of the declared sizes, finite. A file whose
    graph and metadata disagree would load, say ready, and then fail (or mislabel) every
    scan. Raises :class:`ModelLoadError` naming the disagreement."""
    try:
        meta = EncoderMetadata.from_props(session.get_modelmeta().custom_metadata_map)
        check_identity(meta)
    except ValueError as err:
        raise ModelLoadError(f"{path}: {err}") from None
    inputs = [i.name for i in session.get_inputs()]
    outputs = [o.name for o in session.get_outputs()]
    if inputs != [INPUT] or tuple(outputs) != OUTPUTS:
        raise ModelLoadError(
            f"{path} has inputs {inputs} and outputs {outputs}; expected [{INPUT}] and "
            f"{list(OUTPUTS)}"
        )
    p = meta.profile
    x = np.concatenate([parity_image(meta)] * 2)  # two scans: the batch must be free
    try:
        desc, yaw = session.run(list(OUTPUTS), {INPUT: x})
    except Exception as err:  # onnxruntime's own classes
        first = str(err).strip().splitlines()[0][:300] if str(err).strip() else ""
        raise ModelLoadError(
            f"{path}: its graph does not run on the input its metadata describes ({len(x)} "
            f"float32 images of {p.height}×{p.width}, {p.name}): {type(err).__name__}: {first}"
        ) from None
    want = ((2, meta.descriptor_dim), (2, meta.yaw_channels, p.width))
    got = (tuple(np.shape(desc)), tuple(np.shape(yaw)))
    if got != want:
        raise ModelLoadError(
            f"{path}: for two scans its graph gives descriptors of shape {got[0]} and yaw "
            f"features of {got[1]}; its metadata says {want[0]} and {want[1]}"
        )
    if not (np.isfinite(desc).all() and np.isfinite(yaw).all()):
        raise ModelLoadError(f"{path}: its graph gives NaN or infinite outputs for a valid scan")
    return meta


def parity_image(meta: EncoderMetadata) -> np.ndarray:
    """Fixed range images of one scan, (V, 1, H, W) with V the views the graph averages
    itself (1 for most), for the load-time check: ranges across the profile's span with a
    fifth of the pixels empty, as real scans have."""
    p = meta.profile
    rng = np.random.default_rng(0)
    shape = (meta.graph_views, 1, p.height, p.width)
    img = rng.uniform(p.min_range, p.max_range, shape).astype(np.float32)
    img[rng.random(img.shape) < 0.2] = p.empty_value
    return img
