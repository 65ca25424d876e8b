"""File formats written by markerpose, in one place: strict JSON (no NaN or Infinity
tokens, which strict parsers reject: a missing or infinite figure is ``null``)."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np


def jsonable(obj):
    """``obj`` with numpy scalars and arrays as Python numbers and lists, tuples as lists,
    and every non-finite float as None."""
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist())
    if isinstance(obj, (np.bool_, bool)):
        return bool(obj)
    if isinstance(obj, (np.integer, int)):
        return int(obj)
    if isinstance(obj, (np.floating, float)):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, Path):
        return str(obj)
    return obj


def dumps(obj, indent: int | None = 1) -> str:
    """Strict JSON text of ``obj`` (see :func:`jsonable`)."""
    return json.dumps(jsonable(obj), indent=indent, allow_nan=False)


def write_report(out: str | Path, res: dict, report: str) -> Path:
    """An experiment's folder ``out``: ``results.json`` (``res``) and ``report.md`` (``report``)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "results.json", res)
    (out / "report.md").write_text(report + "\n")
    return out


def write_json(path: str | Path, obj, indent: int | None = 1) -> Path:
    """Write ``obj`` as strict JSON; returns the path."""
    path = Path(path)
    path.write_text(dumps(obj, indent) + "\n")
    return path


__all__ = [
    "dumps",
    "jsonable",
    "open_storage",
    "read_ply",
    "read_sequence",
    "read_volume",
    "storage_array",
    "write_json",
    "write_ply",
    "write_sequence",
    "SEQUENCE_SUFFIX",
    "write_volume",
]


# --- OpenCV FileStorage (rig and probe calibration files) ----------------------------
MAX_STORAGE_BYTES = 1 << 20  # a rig file is a few kB
MAX_STORAGE_DEPTH = 32  # nesting of sequences, maps or XML elements (a rig file needs 3)


def storage_depth(text: str) -> int:
    """The deepest nesting of flow sequences / maps (``[`` ``{``), XML elements and block
    indentation (in steps of the smallest indent) in a FileStorage text, counted without
    parsing it: OpenCV's reader recurses per level and crashes the process on deep
    nesting, so the depth is bounded before it sees the file."""
    depth = best = 0
    for ch in text:
        if ch in "[{":
            depth += 1
            best = max(best, depth)
        elif ch in "]}":
            depth = max(depth - 1, 0)
    xml = 0
    for m in re.finditer(r"<(/?)[A-Za-z_][^<>]*?(/?)>", text):
        if m.group(1):
            xml = max(xml - 1, 0)
        elif not m.group(2):
            xml += 1
            best = max(best, xml)
    indents = [len(line) - len(line.lstrip(" ")) for line in text.splitlines() if line.strip()]
    step = min((i for i in indents if i > 0), default=0)
    if step:
        best = max(best, max(indents) // step + 1)
    return best


def open_storage(path: str | Path):
    """An OpenCV FileStorage opened for reading, or a ValueError naming the file.

    The file's size and nesting are bounded first (:data:`MAX_STORAGE_BYTES`,
    :data:`MAX_STORAGE_DEPTH`, :func:`storage_depth`). Opened in two steps: a parse error
    inside the constructor surfaces as a bare SystemError in the Python bindings, whereas
    ``open()`` raises ``cv2.error``.
    """
    import cv2

    size = Path(path).stat().st_size
    if size > MAX_STORAGE_BYTES:
        raise ValueError(f"{path}: {size} bytes; a rig file is a few kB (at most {MAX_STORAGE_BYTES} bytes read)")
    text = Path(path).read_bytes().decode("utf-8", errors="replace")
    depth = storage_depth(text)
    if depth > MAX_STORAGE_DEPTH:
        raise ValueError(f"{path}: nested {depth} levels deep; a rig file needs 3 (at most {MAX_STORAGE_DEPTH} read)")
    fs = cv2.FileStorage()
    try:
        fs.open(str(path), cv2.FILE_STORAGE_READ)
    except cv2.error as e:
        raise ValueError(f"{path}: not a readable OpenCV FileStorage YAML/XML file ({e.err})") from None
    if not fs.isOpened():
        raise ValueError(f"{path}: not a readable OpenCV FileStorage YAML/XML file")
    return fs


def storage_array(fs, key: str, path) -> np.ndarray | None:
    """The matrix (an opencv-matrix map, or a plain sequence of numbers) stored under
    ``key``; None when the key is absent; a ValueError naming the file and key otherwise."""
    import cv2

    node = fs.getNode(key)
    if node.empty() or node.isNone():
        return None
    if node.isMap():
        try:
            m = node.mat()
        except cv2.error:  # a map that is not an opencv-matrix
            m = None
        if m is not None:
            return np.asarray(m)
    elif node.isSeq():
        vals = [node.at(i) for i in range(node.size())]
        if all(v.isReal() or v.isInt() for v in vals):
            return np.array([v.real() for v in vals])
    raise ValueError(f"{path}: key '{key}' is not a matrix")


# --- point clouds ---------------------------------------------------------------------
def write_ply(path: str | Path, points: np.ndarray, frame: np.ndarray | None = None, inlier: np.ndarray | None = None) -> Path:
    """Binary little-endian PLY of (N, 3) points (float32 x y z, mm), with an int32
    ``frame`` property per point and a uchar ``inlier`` flag (1: kept by the fit, 0:
    rejected) when given. Opens in MeshLab, CloudCompare, 3D Slicer."""
    path = Path(path)
    P = np.asarray(points, dtype="<f4").reshape(-1, 3)
    props = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    extra = {"frame": (frame, "<i4"), "inlier": (inlier, "u1")}
    props += [(name, t) for name, (v, t) in extra.items() if v is not None]
    rec = np.empty(len(P), dtype=props)
    rec["x"], rec["y"], rec["z"] = P[:, 0], P[:, 1], P[:, 2]
    for name, (v, t) in extra.items():
        if v is not None:
            v = np.asarray(v).reshape(-1)
            if len(v) != len(P):
                raise ValueError(f"{name}: {len(v)} values for {len(P)} points")
            rec[name] = v.astype(t)
    names = {"<f4": "float", "<i4": "int", "u1": "uchar"}
    header = (
        ["ply", "format binary_little_endian 1.0", "comment markerpose point cloud, millimetres", f"element vertex {len(P)}"]
        + [f"property {names[t]} {n}" for n, t in props]
        + ["end_header"]
    )
    with open(path, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(rec.tobytes())
    return path


def read_ply(path: str | Path) -> dict:
    """Read a binary little-endian PLY vertex list written by :func:`write_ply` (float and
    int properties): a dict of property name → array."""
    types = {"float": "<f4", "float32": "<f4", "double": "<f8", "int": "<i4", "int32": "<i4", "uchar": "u1", "uint8": "u1"}
    with open(path, "rb") as f:
        if f.readline().strip() != b"ply":
            raise ValueError(f"{path}: not a PLY file")
        props, n, fmt = [], 0, None
        while True:
            line = f.readline()
            if not line:
                raise ValueError(f"{path}: PLY header without end_header")
            words = line.decode("ascii").split()
            if not words:
                continue
            if words[0] == "format":
                fmt = words[1]
            elif words[0] == "element" and words[1] == "vertex":
                n = int(words[2])
            elif words[0] == "property":
                if words[1] not in types:
                    raise ValueError(f"{path}: unsupported PLY property type {words[1]}")
                props.append((words[2], types[words[1]]))
            elif words[0] == "end_header":
                break
        if fmt != "binary_little_endian":
            raise ValueError(f"{path}: only binary_little_endian PLY is read, got {fmt}")
        rec = np.frombuffer(f.read(), dtype=props, count=n)
    return {name: np.array(rec[name]) for name, _ in props}


# --- volumes and ultrasound sequences (NRRD, read by 3D Slicer, PLUS, ITK) -------------
def write_volume(path: str | Path, data: np.ndarray, origin, directions) -> Path:
    """A 3D volume as NRRD: ``data`` (nx, ny, nz) indexed [i, j, k]; ``origin`` the centre
    of voxel (0, 0, 0) and ``directions`` (3, 3) whose columns are the steps along i, j, k,
    both in millimetres in the tracker frame. The file's ``space`` is
    right-anterior-superior: 3D Slicer then shows the volume in the tracker frame, as it
    applies the OpenIGTLink transforms (which it takes as RAS), not mirrored (a NRRD
    without ``space`` is read as LPS)."""
    import nrrd

    path = Path(path)
    header = {
        "space": "right-anterior-superior",
        "space directions": np.asarray(directions, dtype=np.float64).T,
        "space origin": np.asarray(origin, dtype=np.float64),
        "space units": ["mm", "mm", "mm"],
        "kinds": ["domain", "domain", "domain"],
        "encoding": "gzip",
    }
    nrrd.write(str(path), np.ascontiguousarray(data), header, index_order="F")
    return path


def read_volume(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(data, origin, directions) of a volume written by :func:`write_volume`, in its
    ``space`` (left-posterior-superior files are turned to right-anterior-superior)."""
    import nrrd

    data, header = nrrd.read(str(path), index_order="F")
    origin, directions = np.asarray(header["space origin"], float), np.asarray(header["space directions"], float).T
    if header.get("space") in ("left-posterior-superior", "LPS"):
        flip = np.diag([-1.0, -1.0, 1.0])
        origin, directions = flip @ origin, flip @ directions
    return data, origin, directions


def _matrix_text(T) -> str:
    return " ".join(f"{v:.9g}" for v in np.asarray(T, dtype=np.float64).ravel())


SEQUENCE_SUFFIX = ".igs.nrrd"  # what SlicerIGSIO's reader registers (PLUS's since 2018; .seq.nrrd is read as plain images)


def write_sequence(path: str | Path, images, timestamps, probe_to_tracker: list, image_to_probe: np.ndarray) -> Path:
    """A tracked ultrasound sweep as a PLUS / IGSIO sequence file (``NAME.igs.nrrd``), which
    3D Slicer (SlicerIGSIO) loads as a sequence browser with its transforms.

    The header is IGSIO's for a 2D image time series (``vtkIGSIONrrdSequenceIO``): sizes
    W H N, kinds ``domain domain list``, ``space dimension`` 2, ``space directions``
    ``(1,0) (0,1) none`` (pixels: the spacing is folded into ImageToProbe), ``space origin``
    ``(0,0)``, ``ultrasound image orientation`` MF; per frame ``Seq_FrameNNNN_`` +
    ``FrameNumber``, ``Timestamp``, ``UnfilteredTimestamp``, ``Status`` (the image's),
    ``ProbeToTrackerTransform`` (+ ``Status``) and ``ImageToProbeTransform`` (+ ``Status``).

    Args:
        images: N uint8 (H, W) frames.
        timestamps: N times, s.
        probe_to_tracker: N (4, 4) ``T_left_marker`` (PLUS's ProbeToTracker) or None where
            the marker was not found (written as identity with status INVALID).
        image_to_probe: (4, 4) PLUS's ImageToProbe (pixels → marker mm, spacing folded in).
    """
    import nrrd

    path = Path(path)
    if not path.name.endswith(SEQUENCE_SUFFIX):
        raise ValueError(f"{path}: a sequence file is named *{SEQUENCE_SUFFIX} (what 3D Slicer's IGSIO reader opens)")
    frames = [np.asarray(im) for im in images]
    if not frames:
        raise ValueError("no frames to write")
    h, w = frames[0].shape
    if any(f.shape != (h, w) or f.dtype != np.uint8 for f in frames):
        raise ValueError("every frame must be uint8 of the same (H, W)")
    if not (len(frames) == len(timestamps) == len(probe_to_tracker)):
        raise ValueError("images, timestamps and probe_to_tracker must have the same length")
    data = np.stack(frames, axis=-1).transpose(1, 0, 2)  # (W, H, N)
    header = {
        "kinds": ["domain", "domain", "list"],
        "encoding": "raw",
        "space dimension": 2,
        "space directions": np.array([[1.0, 0.0], [0.0, 1.0], [np.nan, np.nan]]),
        "space origin": np.zeros(2),
        "ultrasound image orientation": "MF",
        "ultrasound image type": "BRIGHTNESS",
    }
    for k, (t, T) in enumerate(zip(timestamps, probe_to_tracker)):
        p = f"Seq_Frame{k:04d}_"
        header[p + "FrameNumber"] = str(k)
        header[p + "Timestamp"] = f"{float(t):.6f}"
        header[p + "UnfilteredTimestamp"] = f"{float(t):.6f}"
        header[p + "Status"] = "OK"
        header[p + "ProbeToTrackerTransform"] = _matrix_text(np.eye(4) if T is None else T)
        header[p + "ProbeToTrackerTransformStatus"] = "INVALID" if T is None else "OK"
        header[p + "ImageToProbeTransform"] = _matrix_text(image_to_probe)
        header[p + "ImageToProbeTransformStatus"] = "OK"
    nrrd.write(str(path), data, header, index_order="F")
    return path


def read_sequence(path: str | Path) -> dict:
    """Read a file written by :func:`write_sequence`: ``images`` (N, H, W) uint8,
    ``timestamps`` (N,), ``probe_to_tracker`` (list of (4, 4) or None), ``image_to_probe``
    (list of (4, 4))."""
    import nrrd

    data, header = nrrd.read(str(path), index_order="F")
    if data.ndim == 4 and data.shape[2] == 1:  # (W, H, 1, N), as earlier releases wrote
        data = data[:, :, 0, :]
    if data.ndim != 3:
        raise ValueError(f"{path}: expected a (W, H, N) sequence of 2D images, got {data.ndim}D")
    images = data.transpose(2, 1, 0)
    n = images.shape[0]

    def mat(s):
        return np.array([float(v) for v in s.split()]).reshape(4, 4)

    times, p2t, i2p = [], [], []
    for k in range(n):
        p = f"Seq_Frame{k:04d}_"
        times.append(float(header[p + "Timestamp"]))
        ok = header.get(p + "ProbeToTrackerTransformStatus", "OK") == "OK"
        p2t.append(mat(header[p + "ProbeToTrackerTransform"]) if ok else None)
        i2p.append(mat(header[p + "ImageToProbeTransform"]))
    return {"images": np.ascontiguousarray(images), "timestamps": np.array(times), "probe_to_tracker": p2t, "image_to_probe": i2p}
