"""What both networks share at inference: loading a weights file safely and running it.

A network ships twice in ``markerpose/weights/``: ``NAME.onnx`` for inference with ONNX
Runtime, or OpenVINO where chosen (no PyTorch needed; the decoding thresholds tuned at
export ride in the model's metadata), and ``NAME.pt`` for training (``--init``,
``--retune``). :func:`load_network` takes either and returns a :class:`Runner` that maps
numpy inputs to numpy outputs.
"""

from __future__ import annotations

import importlib.util
import json
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np

from .signals import held_interrupt
from .threads import Worker, cores

WEIGHTS_DIR = Path(__file__).parent / "weights"
META_KEY = "markerpose"  # the ONNX metadata entry holding the file's non-weight contents

# The format of the exported weights files (``--export``): a ``format`` entry names the
# network and this number, so a file of the other network, of an older export or not of
# markerpose at all fails at load with a message rather than inside torch.
FORMAT = 1


def load_checkpoint(path: str | Path, kind: str, device: str = "cpu", required: tuple = ("state_dict",)) -> dict:
    """A weights file as a dict, or ``ValueError`` naming the file and what is wrong.

    Args:
        path: the file.
        kind: "keypoints" or "ellipses": the network it must be for. An exported file
            says so in its ``format`` entry ``{"network": kind, "version": FORMAT}``; a
            training checkpoint (``best.pt``/``last.pt``, no ``format``) is accepted
            when it has the ``required`` keys.
        required: keys the dict must have.
    """
    import pickle

    import torch

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{kind} weights not found: {path} (train them with `markerpose train {kind}`)")
    try:
        ckpt = torch.load(path, map_location=device, weights_only=True)
    except (pickle.UnpicklingError, RuntimeError, EOFError, zipfile.BadZipFile, ValueError, OSError, AttributeError, TypeError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ValueError(f"{path} is not a readable PyTorch weights file ({first[:160]})") from exc
    if not isinstance(ckpt, dict):
        raise ValueError(f"{path} is not a markerpose {kind} weights file: holds a {type(ckpt).__name__}")
    fmt = ckpt.get("format")
    if fmt is not None and fmt != {"network": kind, "version": FORMAT}:
        raise ValueError(f"{path} is not a markerpose {kind} weights file of format {FORMAT}: its format is {fmt}")
    if fmt is None and "decode" in ckpt:
        raise ValueError(f"{path} was exported without a format entry (before format {FORMAT}): export it again")
    for key in required:
        if key not in ckpt:
            raise ValueError(f"{path} is not a markerpose {kind} weights file: no {key!r}")
    return ckpt


def load_weights(net, state_dict, path: str | Path) -> None:
    """``net.load_state_dict(state_dict)`` (strict: every weight must match), or ``ValueError``
    naming the file when the weights are for another network or another width."""
    try:
        net.load_state_dict(state_dict)
    except (RuntimeError, KeyError, TypeError, AttributeError) as exc:
        first = str(exc).strip().splitlines()[0][:200]
        raise ValueError(f"{path}: the weights do not fit the network ({first})") from exc


def fuse_batchnorm(net):
    """``net`` (in eval mode) with every ``Conv2d`` followed by a ``BatchNorm2d`` inside an
    ``nn.Sequential`` replaced by one convolution that applies both (the norm becomes an
    ``nn.Identity``). Inference only: the outputs stay the same to float precision, the
    per-pixel norm pass over every feature map is gone. Returns ``net``, changed in place.
    """
    from torch import nn
    from torch.nn.utils.fusion import fuse_conv_bn_eval

    if net.training:
        raise ValueError("fuse_batchnorm is for inference: call net.eval() first")
    for seq in [m for m in net.modules() if isinstance(m, nn.Sequential)]:
        for k in range(len(seq) - 1):
            conv, bn = seq[k], seq[k + 1]
            if isinstance(conv, nn.Conv2d) and isinstance(bn, nn.BatchNorm2d):
                seq[k], seq[k + 1] = fuse_conv_bn_eval(conv, bn), nn.Identity()  # keeps the weights' memory format
    return net


def have_onnxruntime() -> bool:
    return importlib.util.find_spec("onnxruntime") is not None


def default_weights(kind: str) -> Path:
    """The shipped file of the ``kind`` network: the ONNX one where ONNX Runtime is
    installed (the default install), else the PyTorch one."""
    return WEIGHTS_DIR / f"{kind}.onnx" if have_onnxruntime() else WEIGHTS_DIR / f"{kind}.pt"


def int8_weights(kind: str) -> Path:
    """The shipped int8 copy of the ``kind`` network's ONNX weights (:func:`quantize_onnx`;
    ONNX Runtime or OpenVINO run it)."""
    return WEIGHTS_DIR / f"{kind}-int8.onnx"


class Runner:
    """A network ready for inference: ``runner(x)`` with x (B, 1, H, W) float32 → tuple of
    float32 outputs. ``backend`` is "onnxruntime", "openvino", "openvino-bf16" or "torch"."""

    def __init__(self, fn: Callable, backend: str, stacked: bool = False, halves: tuple | None = None):
        self._fn, self.backend = fn, backend
        self.stacked = stacked  # batches of two run by the weights' stacked copy (stack_views)
        # Where a batch runs as two halves at once (two sessions, each on its share of the
        # threads): each half's runner, (x -> outputs, x -> outputs), so that a caller can
        # run each half with its own work before and after it on the half's thread.
        self.halves = halves

    def __call__(self, x: np.ndarray) -> tuple:
        return self._fn(np.ascontiguousarray(x, np.float32))


def _unreadable(path: Path, exc: Exception) -> ValueError:
    """The error for a file a runtime could not read (runtimes raise their own types)."""
    first = str(exc).strip().splitlines()[0][:160] if str(exc).strip() else type(exc).__name__
    return ValueError(f"{path} is not a readable ONNX model ({first})")


def _checked_meta(path: Path, kind: str, raw: str | None) -> dict:
    """An ``.onnx`` file's markerpose metadata (JSON text, None or "" when absent), refused
    unless it is a ``kind`` model of this format."""
    try:
        meta = json.loads(raw) if raw else {}
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: its {META_KEY!r} metadata is not JSON") from exc
    if meta.get("format") != {"network": kind, "version": FORMAT}:
        raise ValueError(f"{path} is not a markerpose {kind} model of format {FORMAT}: its format is {meta.get('format')}")
    return meta


# ONNX Runtime graph rewrites left out: QDQ propagation moves an int8 network's first
# quantization above the max-pool before it, which then runs on int8 in the plain layout,
# slower than the float32 pool in the blocked one (the outputs are the same either way:
# the max commutes with a monotonic quantization).
_SKIPPED_REWRITES = ["QDQPropagationTransformer"]


def _onnx_runner(path: Path, kind: str, threads: int | None, stacked: Path | None = None) -> tuple[Runner, dict]:
    """ONNX Runtime's runner of ``path``; ``stacked``: its :func:`stack_views` copy, which
    then runs every batch of two (where its metadata is that of ``path`` plus the stacking
    entry; else it is left unused)."""
    try:
        with held_interrupt():
            import onnxruntime as ort
    except ImportError as exc:
        raise ValueError(f"{path}: ONNX weights need onnxruntime (pip install onnxruntime)") from exc

    def session(n: int | None, file: Path = path):
        opts = ort.SessionOptions()
        if n:
            opts.intra_op_num_threads = int(n)
        opts.inter_op_num_threads = 1
        # Idle worker threads would otherwise spin after each run, taking the CPU from the
        # rest of the pipeline (and from other sessions, e.g. the other network).
        opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
        try:
            return ort.InferenceSession(str(file), opts, providers=["CPUExecutionProvider"], disabled_optimizers=_SKIPPED_REWRITES)
        except Exception as exc:  # ORT raises its own exception types for unreadable models
            raise _unreadable(file, exc) from exc

    whole = session(threads)
    meta = _checked_meta(path, kind, whole.get_modelmeta().custom_metadata_map.get(META_KEY))
    name = whole.get_inputs()[0].name
    n = int(threads or cores())
    pair = session(n, stacked) if stacked is not None else None
    if pair is not None and json.loads(pair.get_modelmeta().custom_metadata_map.get(META_KEY) or "{}") != {
        **meta,
        "stacked_views": STACK_CHANNELS,
    }:
        pair = None  # not this file's copy (e.g. left from older weights)
    if n < 2 and pair is None:
        return Runner(lambda x: tuple(whole.run(None, {name: x})), "onnxruntime"), meta
    # Otherwise a batch (the two views, a look's windows) runs as two halves at once, each
    # on half the threads: the small layers of these networks leave threads idle at every
    # operator's barrier when one run spreads over all of them.
    halves = (session(n // 2), session(n - n // 2)) if n >= 2 else None
    worker = Worker()

    def half(h):
        return lambda x: tuple(h.run(None, {name: np.ascontiguousarray(x, np.float32)}))

    parts = tuple(half(h) for h in halves) if halves is not None else None

    def run(x):
        if pair is not None and len(x) == 2:
            return tuple(pair.run(None, {name: x.reshape(1, 2, *x.shape[2:])}))
        if len(x) < 2 or parts is None:
            return tuple(whole.run(None, {name: x}))
        k = len(x) // 2
        first, second = worker.both(lambda: parts[0](x[:k]), lambda: parts[1](x[k:]))
        return tuple(np.concatenate(both) for both in zip(first, second))

    return Runner(run, "onnxruntime", stacked=pair is not None, halves=parts if pair is None else None), meta


BACKENDS = ("onnxruntime", "openvino", "openvino-bf16")  # how ``.onnx`` weights run


def _openvino_runner(path: Path, kind: str, threads: int | None, bf16: bool) -> tuple[Runner, dict]:
    """The ``.onnx`` file on OpenVINO's CPU plugin, compiled once for any batch and input
    size; ``bf16``: bfloat16 inference (fast on CPUs with AMX; the outputs are not
    float32's)."""
    try:
        import openvino as ov
    except ImportError as exc:
        raise ValueError(f'{path}: the openvino backend needs OpenVINO (pip install -e ".[openvino]")') from exc
    core = ov.Core()
    try:
        model = core.read_model(str(path))
    except Exception as exc:  # OpenVINO raises its own exception types for unreadable models
        raise _unreadable(path, exc) from exc
    try:
        raw = model.get_rt_info(["framework", META_KEY]).astype(str)
    except RuntimeError:  # no such entry: not a markerpose file (refused below)
        raw = ""
    meta = _checked_meta(path, kind, raw)
    config = {"PERFORMANCE_HINT": "LATENCY", "INFERENCE_PRECISION_HINT": "bf16" if bf16 else "f32"}
    if threads:
        config["INFERENCE_NUM_THREADS"] = int(threads)
    request = core.compile_model(model, "CPU", config).create_infer_request()
    outputs = len(model.outputs)

    def run(x):
        request.infer({0: x})
        return tuple(request.get_output_tensor(i).data.copy() for i in range(outputs))

    return Runner(run, "openvino-bf16" if bf16 else "openvino"), meta


def have_backend(backend: str) -> bool:
    """Whether ``.onnx`` weights can run on ``backend`` here (its package is installed)."""
    try:
        return importlib.util.find_spec("openvino" if backend.startswith("openvino") else backend) is not None
    except (ImportError, ValueError):  # a broken or blocked installation
        return False


def _torch_runner(path: Path, kind: str, build: Callable[[dict], object], device: str, required: tuple) -> tuple[Runner, dict]:
    import torch

    ckpt = load_checkpoint(path, kind, device, required=required)
    net = build(ckpt).to(device).eval()
    load_weights(net, ckpt["state_dict"], path)
    fuse_batchnorm(net)

    def run(x):
        with torch.inference_mode():
            out = net(torch.from_numpy(x).to(device))
        out = out if isinstance(out, tuple) else (out,)
        return tuple(o.float().cpu().numpy() for o in out)

    return Runner(run, "torch"), {k: v for k, v in ckpt.items() if k != "state_dict"}


def load_network(
    path: str | Path | None,
    kind: str,
    build: Callable[[dict], object],
    threads: int | None = None,
    device: str = "cpu",
    required: tuple = ("state_dict",),
    backend: str = "onnxruntime",
    stack_views: bool = False,
) -> tuple[Runner, dict, Path]:
    """A network and what its file says besides the weights (format, width, tuned
    thresholds, metrics), from an ``.onnx`` file (ONNX Runtime or OpenVINO) or a ``.pt``
    one (PyTorch).

    Args:
        path: the file (None: :func:`default_weights`).
        kind: "keypoints" or "ellipses".
        build: meta → the torch module to load ``.pt`` weights into.
        threads: the runtime's threads (None: its default, every core).
        backend: what runs ``.onnx`` weights (:data:`BACKENDS`): ONNX Runtime, or OpenVINO
            at float32 or bfloat16.
        stack_views: on ONNX Runtime, run batches of two by the file's :func:`stack_views`
            copy where one lies beside it with the same metadata.
    Returns:
        (runner, meta, path).
    """
    if backend not in BACKENDS:
        raise ValueError(f"unknown backend {backend!r}; choose from {BACKENDS}")
    path = Path(path) if path is not None else default_weights(kind)
    if not path.is_file():
        how = (
            f"make them with `markerpose train {kind} --int8 SRC DEST`"
            if path == int8_weights(kind)
            else f"train them with `markerpose train {kind}`"
        )
        raise ValueError(f"{kind} weights not found: {path} ({how})")
    if backend != "onnxruntime" and path.suffix != ".onnx":
        raise ValueError(f"{path}: the {backend} backend runs .onnx weights only")
    if path.suffix == ".onnx" and backend != "onnxruntime":
        return (*_openvino_runner(path, kind, threads, backend == "openvino-bf16"), path)
    if path.suffix == ".onnx":
        stacked = stacked_views_path(path)
        return (*_onnx_runner(path, kind, threads, stacked if stack_views and stacked.is_file() else None), path)
    if importlib.util.find_spec("torch") is None:
        raise ValueError(
            f"{path}: PyTorch checkpoints need PyTorch (the train extra); inference runs the .onnx copy that "
            f"`markerpose train {kind} --export` writes beside it"
        )
    return (*_torch_runner(path, kind, build, device, required), path)


def export_onnx(net, path: str | Path, example_shape: tuple, kind: str, meta: dict, output_names: tuple, dynamic_hw: bool = False) -> Path:
    """Write an inference copy of a torch network (eval mode, batch norm folded) as ONNX,
    with ``meta`` (JSON) and the format entry in its metadata. Needs ``onnx`` (the train extra)."""
    import onnx
    import torch

    path = Path(path)
    axes = {0: "batch", **({2: "height", 3: "width"} if dynamic_hw else {})}
    dynamic = {"image": axes, **dict.fromkeys(output_names, axes)}
    import warnings

    with torch.no_grad(), warnings.catch_warnings():
        # The TorchScript exporter needs no onnxscript; its deprecation notice is not for users.
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.onnx.export(
            net,
            torch.zeros(example_shape),
            str(path),
            input_names=["image"],
            output_names=list(output_names),
            dynamic_axes=dynamic,
            opset_version=17,
            dynamo=False,
        )
    model = onnx.load(str(path))
    entry = model.metadata_props.add()
    entry.key, entry.value = META_KEY, json.dumps({"format": {"network": kind, "version": FORMAT}, **meta})
    onnx.save(model, str(path))
    return path


def detector_only_path(path: str | Path) -> Path:
    """Where the detector-head-only copy of stage-1 weights ``path`` lies (:func:`detector_only`)."""
    path = Path(path)
    return path.with_name(f"{path.stem}-det.onnx")


def detector_only(src: str | Path, dest: str | Path | None = None) -> Path:
    """A copy of an ``.onnx`` stage-1 network that computes only its detector head's output
    ("det"; the ID head's layers left out), with the same metadata plus ``detector_only``.
    Stage 1's candidates need no ID head; ONNX Runtime runs every layer of a graph whatever
    outputs are asked for. ``dest`` defaults to :func:`detector_only_path`. Needs ``onnx``."""
    import tempfile

    import onnx
    from onnx.utils import extract_model

    src = Path(src)
    model = onnx.load(str(src))
    meta = _checked_meta(src, "keypoints", _meta_text(model))
    dest = Path(dest) if dest is not None else detector_only_path(src)
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "det.onnx"
        extract_model(str(src), str(out), [model.graph.input[0].name], ["det"])
        det = onnx.load(str(out))
    for m in list(det.metadata_props):
        det.metadata_props.remove(m)
    entry = det.metadata_props.add()
    entry.key, entry.value = META_KEY, json.dumps({**meta, "detector_only": True})
    onnx.save(det, str(dest))
    return dest


def stacked_views_path(path: str | Path) -> Path:
    """Where the :func:`stack_views` copy of stage-1 weights ``path`` lies."""
    path = Path(path)
    return path.with_name(f"{path.stem}-pair.onnx")


# ONNX Runtime's blocked convolutions work on this many channels at a time on CPUs with
# AVX-512 (8 with AVX2): a layer with fewer output channels costs about as much as one
# with this many. :func:`stack_views` stacks the two views' layers narrower than this.
STACK_CHANNELS = 16


def wide_vectors() -> bool:
    """Whether this CPU has AVX-512, where ONNX Runtime's convolutions work on
    :data:`STACK_CHANNELS` channels at a time (the stacked copies pay there; with 8-wide
    blocks, their zero blocks would double the narrow layers' work)."""
    try:
        import llvmlite.binding as llvm  # numba's, installed with it

        return bool(llvm.get_host_cpu_features().get("avx512f", False))
    except Exception:  # no feature list on this platform: assume narrow vectors
        return False


def stack_views(src: str | Path, dest: str | Path | None = None) -> Path:
    """A copy of an ``.onnx`` stage-1 network that takes a batch of two images as the two
    channels of one input (1, 2, H, W) and gives what the network gives the batch (2, 1,
    H, W): its first convolutions narrower than :data:`STACK_CHANNELS` (and the ReLUs and
    max-pools between them) work on both images at once, their weights block-diagonal
    (each image's channels see only its own), and a reshape then makes the two a batch
    again. Why: ONNX Runtime pads such narrow layers to :data:`STACK_CHANNELS` channels on
    CPUs with AVX-512, so the two images' stem costs about what one image's did.

    The same metadata plus ``stacked_views``; ``dest`` defaults to
    :func:`stacked_views_path`. ``ValueError`` when the network starts with no such
    layer. Needs ``onnx``."""
    import onnx
    from onnx import helper, numpy_helper

    src = Path(src)
    model = onnx.load(str(src))
    meta = _checked_meta(src, "keypoints", _meta_text(model))
    if "stacked_views" in meta:
        raise ValueError(f"{src} is already a stacked copy")
    graph = model.graph
    inits = {t.name: t for t in graph.initializer}
    consumers: dict[str, list] = {}
    for node in graph.node:
        for x in node.input:
            consumers.setdefault(x, []).append(node)
    cur, stacked = graph.input[0].name, 0
    # Follow the chain from the input while it is one narrow convolution, ReLU or max-pool
    # after another (each tensor read by that node only).
    while len(consumers.get(cur, [])) == 1:
        node = consumers[cur][0]
        if node.op_type == "Conv":
            group = next((a.i for a in node.attribute if a.name == "group"), 1)
            if group != 1 or node.input[1] not in inits or (len(node.input) > 2 and node.input[2] not in inits):
                break
            w = numpy_helper.to_array(inits[node.input[1]])
            if w.shape[0] >= STACK_CHANNELS:
                break
            co, ci = w.shape[:2]
            both = np.zeros((2 * co, 2 * ci, *w.shape[2:]), w.dtype)
            both[:co, :ci], both[co:, ci:] = w, w
            inits[node.input[1]].CopyFrom(numpy_helper.from_array(both, node.input[1]))
            if len(node.input) > 2:
                b = numpy_helper.to_array(inits[node.input[2]])
                inits[node.input[2]].CopyFrom(numpy_helper.from_array(np.concatenate([b, b]), node.input[2]))
            stacked, channels = stacked + 1, co
        elif node.op_type not in ("Relu", "MaxPool"):
            break
        cur = node.output[0]
    if not stacked:
        raise ValueError(f"{src} starts with no convolution narrower than {STACK_CHANNELS} channels: nothing to stack")
    # (1, 2 C, h, w) -> (2, C, h, w): the first C channels are the first image's.
    shape = f"{cur}_views_shape"
    graph.initializer.append(numpy_helper.from_array(np.array([2, channels, 0, 0], np.int64), shape))
    for node in consumers.get(cur, []):
        for k, x in enumerate(node.input):
            if x == cur:
                node.input[k] = f"{cur}_views"
    for k, out in enumerate(graph.output):
        if out.name == cur:  # a network that is all stem: its output is the batch too
            graph.output[k].name = f"{cur}_views"
    at = next(i for i, node in enumerate(graph.node) if cur in node.output) + 1
    graph.node.insert(at, helper.make_node("Reshape", [cur, shape], [f"{cur}_views"], name="views_to_batch"))
    dims = graph.input[0].type.tensor_type.shape.dim
    dims[0].dim_value, dims[1].dim_value = 1, 2
    del graph.value_info[:]  # the shapes inferred for one image per batch item
    for m in list(model.metadata_props):
        model.metadata_props.remove(m)
    entry = model.metadata_props.add()
    entry.key, entry.value = META_KEY, json.dumps({**meta, "stacked_views": STACK_CHANNELS})
    onnx.checker.check_model(model)
    dest = Path(dest) if dest is not None else stacked_views_path(src)
    onnx.save(model, str(dest))
    return dest


def candidate_copies(path: str | Path) -> list[Path]:
    """What stage 1's candidates run, written beside stage-1 weights ``path``: the
    :func:`detector_only` copy, and its :func:`stack_views` copy where the network starts
    narrow. Needs ``onnx``."""
    det = detector_only(path)
    try:
        return [det, stack_views(det)]
    except ValueError:  # a stem of full blocks: nothing to stack
        return [det]


def _meta_text(model) -> str | None:
    """A loaded ONNX model's markerpose metadata text (None when absent)."""
    return next((m.value for m in model.metadata_props if m.key == META_KEY), None)


def quantizable_meta(src: str | Path, kind: str | None = None) -> dict:
    """The markerpose metadata of an ``.onnx`` network that :func:`quantize_onnx` can
    quantize (of network ``kind`` when given), or ``ValueError`` saying why not. Needs
    ``onnx``."""
    import onnx
    from google.protobuf.message import DecodeError

    src = Path(src)
    if not src.is_file():
        raise ValueError(f"no such file: {src}")
    try:
        model = onnx.load(str(src), load_external_data=False)
    except (DecodeError, ValueError, OSError) as exc:
        raise ValueError(f"{src} is not a readable ONNX model") from exc
    raw = _meta_text(model)
    if kind:
        meta = _checked_meta(src, kind, raw)
    else:
        try:
            meta = json.loads(raw) if raw else {}
        except json.JSONDecodeError:
            meta = {}
        if "format" not in meta:
            raise ValueError(f"{src} is not a markerpose ONNX model (no {META_KEY!r} metadata)")
    if "int8" in meta:
        raise ValueError(f"{src} is already quantized")
    return meta


def quantize_onnx(src: str | Path, dest: str | Path, batches: list) -> Path:
    """An int8 copy of an ``.onnx`` network: weights per output channel, activations per
    tensor (unsigned), as QuantizeLinear/DequantizeLinear pairs around each operator, the
    activations' ranges calibrated (min-max) on ``batches`` ((B, 1, H, W) float32 inputs
    in [0, 1]); the input's range is [0, 1] whatever the batches hold. The operators that
    produce the network's outputs stay float32: quantized logits lose the resolution that
    ranks stage 1's candidates (a small marker's rings among them); so do the narrow ones
    (:data:`INT8_MIN_CHANNELS`) and those reading the one-channel input, where int8 runs
    slower. The markerpose
    metadata is kept, with ``int8`` (the number of calibration inputs) added. Needs
    ``onnx`` (the train extra) to make; the result runs without it, on ONNX Runtime (or
    OpenVINO)."""
    import tempfile

    import onnx
    from onnxruntime.quantization.shape_inference import quant_pre_process

    src, dest = Path(src), Path(dest)
    meta = quantizable_meta(src)
    batches = [np.ascontiguousarray(b, np.float32) for b in batches]
    if not batches:
        raise ValueError("quantize_onnx needs calibration inputs")

    with tempfile.TemporaryDirectory() as tmp:
        pre = Path(tmp) / "pre.onnx"
        # Shape inference and graph fusions first, as the tool advises (ONNX's own shape
        # inference: the symbolic one needs sympy, and this network's shapes need none).
        quant_pre_process(str(src), str(pre), skip_symbolic_shape=True)
        _quantize_qdq(pre, dest, batches)
    out = onnx.load(str(dest))
    _drop_unused_opsets(out)
    for m in list(out.metadata_props):
        if m.key == META_KEY:
            out.metadata_props.remove(m)
    entry = out.metadata_props.add()
    entry.key, entry.value = META_KEY, json.dumps({**meta, "int8": {"calibration_inputs": int(sum(len(b) for b in batches))}})
    onnx.save(out, str(dest))
    return dest


def _quantize_qdq(pre: Path, dest: Path, batches: list) -> None:
    """Quantize the prepared network ``pre`` into ``dest`` (see :func:`quantize_onnx`):
    QDQ pairs, weights per channel, activations calibrated on ``batches``, the input
    pinned to [0, 1] and the output operators left float32."""
    import onnx
    from onnxruntime.quantization import (
        CalibrationDataReader,
        QuantFormat,
        QuantType,
        quantize_static,
    )

    graph = onnx.load(str(pre)).graph
    name = graph.input[0].name

    class Reader(CalibrationDataReader):
        def __init__(self):
            self._it = iter(batches)

        def get_next(self):
            b = next(self._it, None)
            return None if b is None else {name: b}

    outputs = {o.name for o in graph.output}
    last = [n.name for n in graph.node if outputs & set(n.output)]
    # Those that read the input stay float32 too: on one grey channel an int8 convolution
    # has too little to multiply per pixel to repay its quantize and dequantize steps.
    first = [n.name for n in graph.node if name in n.input]
    narrow = _narrow_nodes(graph)
    pinned = {name: [{"rmin": np.float32(0.0), "rmax": np.float32(1.0)}]}
    quantize_static(
        str(pre),
        str(dest),
        Reader(),
        quant_format=QuantFormat.QDQ,
        per_channel=True,
        activation_type=QuantType.QUInt8,
        weight_type=QuantType.QInt8,
        nodes_to_exclude=last + first + narrow,
        extra_options={"TensorQuantOverrides": pinned},
    )


# Operators whose output has fewer channels than this stay float32: ONNX Runtime's int8
# convolutions are slower than its float32 ones on layers this narrow (the stem of the
# stage-1 networks, at full and half resolution), and faster on the wider ones after it.
INT8_MIN_CHANNELS = 16


def _narrow_nodes(graph) -> list[str]:
    """Names of ``graph``'s operators (shapes inferred) whose (N, C, H, W) output has fewer
    than :data:`INT8_MIN_CHANNELS` channels C."""
    channels = {}
    for v in [*graph.value_info, *graph.output]:
        dims = v.type.tensor_type.shape.dim
        if len(dims) == 4 and dims[1].HasField("dim_value"):
            channels[v.name] = dims[1].dim_value
    return [n.name for n in graph.node if 0 < channels.get(n.output[0], INT8_MIN_CHANNELS) < INT8_MIN_CHANNELS]


def _drop_unused_opsets(model) -> None:
    """Remove from ``model`` the operator sets its nodes do not use (the default one
    stays): the quantization tool declares every domain the installed runtime knows,
    which older runtimes refuse to load."""
    used = {n.domain for n in model.graph.node}
    for op in [o for o in model.opset_import if o.domain not in used and o.domain not in ("", "ai.onnx")]:
        model.opset_import.remove(op)


__all__ = [
    "BACKENDS",
    "FORMAT",
    "Runner",
    "default_weights",
    "detector_only",
    "detector_only_path",
    "export_onnx",
    "fuse_batchnorm",
    "have_backend",
    "have_onnxruntime",
    "int8_weights",
    "load_checkpoint",
    "load_network",
    "load_weights",
    "quantizable_meta",
    "quantize_onnx",
]
