"""``markerpose handeye``: the tracker's cameras and a robot in one frame."""

from __future__ import annotations

import csv
from pathlib import Path


def read_robot_csv(path) -> tuple:
    """Times (s) and T_base_gripper (N, 4, 4, mm) of a robot CSV (``timestamp_s,T00,…,T33``)."""
    import numpy as np

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: no such file")
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    need = ["timestamp_s"] + [f"T{i}{j}" for i in range(4) for j in range(4)]
    if not rows or any(k not in rows[0] for k in need):
        raise ValueError(f"{path}: a robot CSV has the columns timestamp_s,T00,…,T33 (T_base_gripper, mm)")
    times, poses = [], []
    for k, r in enumerate(rows):
        try:
            times.append(float(r["timestamp_s"]))
            poses.append(np.array([float(r[f"T{i}{j}"]) for i in range(4) for j in range(4)]).reshape(4, 4))
        except (TypeError, ValueError):
            raise ValueError(f"{path}: row {k + 2} is not a complete pose row") from None
    return np.array(times), np.stack(poses)


def cmd_handeye(args):
    import numpy as np
    import yaml

    from ..handeye import advice, hand_eye, pair_by_time
    from ..video import read_track_csv

    t_robot, A = read_robot_csv(args.robot)
    t_poses, poses, frame = read_track_csv(args.poses, args.tool)
    if frame != "camera":
        raise ValueError(f"{args.poses}: the poses are relative to {frame!r}; hand-eye calibration takes poses in the camera's frame")
    seen = [k for k, T in enumerate(poses) if T is not None]
    pairs = pair_by_time(t_robot, t_poses[seen], args.tolerance)
    if not pairs:
        raise ValueError(
            f"no robot row has a found pose within {args.tolerance:g} s ({len(t_robot)} robot rows, {len(seen)} poses found): "
            "are both files on the same clock? (--tolerance)"
        )
    A_p = A[[i for i, _ in pairs]]
    B_p = np.stack([poses[seen[j]] for _, j in pairs])
    results = hand_eye(A_p, B_p, args.setup)
    names = ("T_gripper_marker", "T_base_camera") if args.setup == "eye-to-hand" else ("T_gripper_camera", "T_base_marker")
    best = results[args.method]
    out = {
        "setup": args.setup,
        "method": args.method,
        names[0]: best.X.tolist(),
        names[1]: best.Z.tolist(),
        "pairs": len(pairs),
        "robot_rows": int(len(t_robot)),
        "tolerance_s": args.tolerance,
        "methods": {m: r.summary() for m, r in results.items()},
        "advice": advice(A_p, len(pairs)),
    }
    Path(args.out).write_text(yaml.safe_dump(out, sort_keys=False, default_flow_style=None))
    print(f"{len(pairs)} pairs of {len(t_robot)} robot rows within {args.tolerance:g} s")
    print("| method | rotation RMS (°) | translation RMS (mm) | translation max (mm) |")
    print("|---|---|---|---|")
    for m, r in results.items():
        s = r.summary()
        print(f"| {m} | {s['rotation_rms_deg']:.4f} | {s['translation_rms_mm']:.4f} | {s['translation_max_mm']:.4f} |")
    for tip in out["advice"]:
        print(f"advice: {tip}")
    print(f"wrote {args.out} ({names[0]}, {names[1]}: {args.method})")
    return 0


def register(sub) -> None:
    p = sub.add_parser("handeye", help="hand-eye calibration: the cameras and a robot in one frame, from robot poses and track's poses")
    p.add_argument("--robot", required=True, help="robot CSV: timestamp_s,T00,…,T33 (T_base_gripper, mm)")
    p.add_argument("--poses", required=True, help="markerpose track's CSV of the marker at those robot poses")
    p.add_argument(
        "--setup", required=True, choices=["eye-to-hand", "eye-in-hand"], help="cameras fixed (marker on the gripper) or on the gripper"
    )
    p.add_argument("--out", default="handeye.yaml", help="the result (YAML; default handeye.yaml)")
    p.add_argument("--tool", help="with several tools in the poses CSV: the tool's name")
    p.add_argument(
        "--tolerance", type=float, default=0.02, help="pair a robot row with the pose nearest in time within this, s (default 0.02)"
    )
    p.add_argument("--method", default="refined", choices=["linear", "refined"], help="which method's result to write (both are compared)")
    p.set_defaults(func=cmd_handeye)
