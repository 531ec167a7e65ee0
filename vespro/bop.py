"""Interchange with the BOP benchmark format (Hodan et al., bop.felk.cvut.cz).

Export (:func:`export_bop`) writes a recording, and optionally tracker output,
as a BOP dataset::

    <out>/
      models/obj_000001.ply         the CAD model in millimetres (ASCII PLY)
      models/models_info.json       diameter, min/size per axis, symmetries_discrete (mm)
      camera.json                   width/height/fx/fy/cx/cy of the first camera
      test/<scene_id:06d>/          one BOP "scene" per rig camera (scene_id = rig index + 1)
        scene_camera.json           per image: cam_K, depth_scale, cam_R_w2c, cam_t_w2c (mm)
        scene_gt.json               per image: [{obj_id, cam_R_m2c, cam_t_m2c (mm)}]  (with ground truth)
        gray/<im_id:06d>.png or rgb/<im_id:06d>.png
      vespro_<object>-test.csv      BOP19 results: scene_id,im_id,obj_id,score,R,t,time  (with --poses)
      vespro.json                   what BOP has no field for: camera names and mounts, capture times

``im_id`` is the recording's frame index. Rotations are row-major 3x3,
translations in mm, ``time`` in seconds (the tracker's per-frame time).
``scene_camera.json`` entries also carry ``width``, ``height`` and
``dist_coeffs`` (plumb_bob; images are exported as captured, not undistorted:
BOP tools assume undistorted images, which holds for our rigs without
distortion). BOP readers ignore keys they do not know.

Import (:func:`import_bop`) turns BOP scenes back into a recording (plus
``groundtruth.csv`` from ``scene_gt.json`` and ``poses.csv`` from a results
CSV). With the ``vespro.json`` of an export the rig is restored exactly;
without it, each scene becomes a camera ``cam<scene_id>``, fixed when its
``cam_R_w2c``/``cam_t_w2c`` never change (or are absent: the world is then
that camera's frame), eye-in-hand with per-frame poses otherwise.
"""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import yaml

from .metrics import discrete_symmetries
from .model import load_model
from .se3 import invert_transform, transform_from_rt

__all__ = ["export_bop", "import_bop", "write_ply_mm", "read_results_csv", "RESULTS_HEADER"]

RESULTS_HEADER = ["scene_id", "im_id", "obj_id", "score", "R", "t", "time"]
OBJ_ID = 1
MM = 1000.0


def _fl(a) -> list[float]:
    return [float(x) for x in np.asarray(a, dtype=float).ravel()]


def write_ply_mm(path: Path, vertices_m: np.ndarray, triangles: np.ndarray) -> None:
    """ASCII PLY of a triangle mesh with vertices in millimetres (BOP's model unit)."""
    V = np.asarray(vertices_m, dtype=float) * MM
    lines = ["ply", "format ascii 1.0", f"element vertex {len(V)}", "property float x", "property float y",
             "property float z", f"element face {len(triangles)}", "property list uchar int vertex_indices",
             "end_header"]
    lines += [f"{float(x)!r} {float(y)!r} {float(z)!r}" for x, y, z in V]
    lines += [f"3 {a} {b} {c}" for a, b, c in np.asarray(triangles, dtype=int)]
    Path(path).write_text("\n".join(lines) + "\n")


def _models_info(model) -> dict:
    lo, hi = model.bounds
    syms = discrete_symmetries(model.vertices)[1:]  # BOP lists the non-identity symmetries
    sd = []
    for S in syms:
        S = S.copy()
        S[:3, 3] *= MM
        sd.append(_fl(S))
    info = {"diameter": model.diameter * MM, "min_x": lo[0] * MM, "min_y": lo[1] * MM, "min_z": lo[2] * MM,
            "size_x": (hi[0] - lo[0]) * MM, "size_y": (hi[1] - lo[1]) * MM, "size_z": (hi[2] - lo[2]) * MM}
    if sd:
        info["symmetries_discrete"] = sd
    return {str(OBJ_ID): info}


def export_bop(recording, out: str | Path, poses: str | Path | None = None,
               overwrite: bool = False, warn=None) -> Path:
    """Write a recording (and optionally its tracker output ``poses.csv``) as a BOP dataset.

    Parameters
    ----------
    recording : path or Recording
        Recording folder (shared/spec/recording.md); its ``groundtruth.csv``,
        when present, becomes ``scene_gt.json`` (frames whose true pose is
        not finite are left out of it). Images that cannot be used (see
        :mod:`vespro.imagecheck`) are not copied; they are counted in the
        recording's ``images``.
    out : path
        Dataset folder to create.
    poses : path, optional
        ``poses.csv``: its ``tracking`` rows become the BOP19 results CSV.
    warn : callable, optional
        Receives a line for each thing about the input that does not stop the
        export (gaps in the ground truth, rows past the end of frames.csv).

    Returns
    -------
    Path
        ``out``.
    """
    from .groundtruth import truth_per_frame
    from .poses import read_poses
    from .recording import Recording

    rec = recording if isinstance(recording, Recording) else Recording(recording)
    model = load_model(rec.model_path, name=rec.object_name)
    out = Path(out)
    if out.exists() and any(out.iterdir()):
        if not overwrite:
            raise FileExistsError(f"{out}: exists and is not empty")
        shutil.rmtree(out)
    (out / "models").mkdir(parents=True, exist_ok=True)
    write_ply_mm(out / "models" / f"obj_{OBJ_ID:06d}.ply", model.vertices, model.triangles)
    (out / "models" / "models_info.json").write_text(json.dumps(_models_info(model), indent=2))
    c0 = rec.rig.cameras[0].intrinsics
    (out / "camera.json").write_text(json.dumps({"cx": c0.cx, "cy": c0.cy, "depth_scale": 1.0, "fx": c0.fx,
                                                 "fy": c0.fy, "height": c0.height, "width": c0.width}, indent=2))
    T_true = None
    if (rec.path / "groundtruth.csv").is_file():
        T_true = truth_per_frame(rec.path, len(rec), warn)
    rows = read_poses(poses) if poses is not None else None
    results = []
    cams_meta = []
    for k, cam in enumerate(rec.rig):
        sid = k + 1
        sdir = out / "test" / f"{sid:06d}"
        sdir.mkdir(parents=True)
        kind = None
        scene_camera, scene_gt = {}, {}
        intr = cam.intrinsics
        for i in range(len(rec)):
            T_cw = invert_transform(rec.T_world_camera(cam.name, i))
            scene_camera[str(i)] = {"cam_K": _fl(intr.K), "depth_scale": 1.0, "cam_R_w2c": _fl(T_cw[:3, :3]),
                                    "cam_t_w2c": _fl(T_cw[:3, 3] * MM), "width": intr.width,
                                    "height": intr.height, "dist_coeffs": _fl(intr.dist)}
            if T_true is not None and np.all(np.isfinite(T_true[i])):
                T_co = T_cw @ T_true[i]
                scene_gt[str(i)] = [{"obj_id": OBJ_ID, "cam_R_m2c": _fl(T_co[:3, :3]),
                                     "cam_t_m2c": _fl(T_co[:3, 3] * MM)}]
            src = rec.check_image(cam.name, i)
            if src.reason is None:
                if kind is None:
                    kind = "gray" if src.grey else "rgb"
                    (sdir / kind).mkdir()
                shutil.copyfile(src.path, sdir / kind / f"{i:06d}.png")
            if rows is not None and i < len(rows) and rows[i].status == "tracking" and rows[i].T_world_object is not None:
                T_co = T_cw @ rows[i].T_world_object
                tm = rows[i].time_ms
                results.append([sid, i, OBJ_ID, 1.0, " ".join(repr(x) for x in _fl(T_co[:3, :3])),
                                " ".join(repr(x) for x in _fl(T_co[:3, 3] * MM)),
                                -1 if tm is None or not np.isfinite(tm) else tm / 1e3])
        (sdir / "scene_camera.json").write_text(json.dumps(scene_camera, indent=1))
        if T_true is not None:
            (sdir / "scene_gt.json").write_text(json.dumps(scene_gt, indent=1))
        cm = {"scene_id": sid, "name": cam.name, "mount": cam.mount}
        if not cam.is_fixed:
            cm["link"] = cam.link
            cm["T_link_camera"] = _fl(cam.T_link_camera)
        cams_meta.append(cm)
    meta = {"format": "vespro-bop-export", "version": 1, "object": rec.object_name, "obj_id": OBJ_ID,
            "rate_hz": rec.rate_hz, "t": _fl(rec.t), "cameras": cams_meta}
    (out / "vespro.json").write_text(json.dumps(meta, indent=1))
    if rows is not None:
        with open(out / f"vespro_{rec.object_name}-test.csv", "w", newline="") as f:
            w = csv.writer(f, lineterminator="\n")
            w.writerow(RESULTS_HEADER)
            w.writerows(results)
    return out


def read_results_csv(path: str | Path) -> list[dict]:
    """BOP19 results rows: dicts with scene_id, im_id, obj_id, score, R (3, 3), t (3,) mm, time s."""
    out = []
    with open(path, newline="") as f:
        r = csv.reader(f)
        header = [h.strip() for h in next(r)]
        if header[:7] != RESULTS_HEADER:
            raise ValueError(f"{path}: header must be {','.join(RESULTS_HEADER)}, got {','.join(header)}")
        for line, row in enumerate(r, start=2):
            if not row:
                continue
            try:
                R = np.array([float(x) for x in row[4].split()]).reshape(3, 3)
                t = np.array([float(x) for x in row[5].split()]).reshape(3)
                out.append({"scene_id": int(row[0]), "im_id": int(row[1]), "obj_id": int(row[2]),
                            "score": float(row[3]), "R": R, "t": t, "time": float(row[6])})
            except (ValueError, IndexError):
                raise ValueError(f"{path}: line {line}: malformed row") from None
    return out


def _find_scenes(bop_dir: Path) -> list[Path]:
    if (bop_dir / "scene_camera.json").is_file():
        return [bop_dir]
    for split in ["test", "val", "train"] + sorted(p.name for p in bop_dir.iterdir() if p.is_dir()):
        d = bop_dir / split
        if d.is_dir():
            scenes = sorted(p for p in d.iterdir() if (p / "scene_camera.json").is_file())
            if scenes:
                return scenes
    raise FileNotFoundError(f"{bop_dir}: no BOP scene (a folder with scene_camera.json) found")


def _T_from_rt_mm(R, t_mm) -> np.ndarray:
    return transform_from_rt(np.asarray(R, dtype=float).reshape(3, 3), np.asarray(t_mm, dtype=float) / MM)


def _image_file(sdir: Path, im_id: int) -> Path | None:
    for kind in ("rgb", "gray"):
        for ext in (".png", ".jpg", ".tif"):
            p = sdir / kind / f"{im_id:06d}{ext}"
            if p.is_file():
                return p
    return None


def _imread(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError(f"{path}: cannot read this image (damaged, or not an image file); replace or remove it")
    return img


def import_bop(bop_dir: str | Path, out: str | Path, results: str | Path | None = None, obj_id: int | None = None,
               rate_hz: float = 26.0, overwrite: bool = False) -> dict:
    """Turn BOP scenes (one per camera, images synchronised by ``im_id``) into a recording.

    Parameters
    ----------
    bop_dir : path
        A BOP dataset folder (scenes under ``test/``, ``val/`` or ``train/``),
        or one scene folder.
    out : path
        Recording folder to create; gets ``groundtruth.csv`` when the scenes
        have ``scene_gt.json`` and ``poses.csv`` when a results CSV is given
        (or ``bop_dir`` holds exactly one ``*.csv``).
    results : path, optional
        BOP19 results CSV.
    obj_id : int, optional
        Object to import (default: the export's, else 1).
    rate_hz : float
        Capture rate when ``vespro.json`` does not give times.

    Returns
    -------
    dict
        ``recording`` (Path), ``T_true`` ((N, 4, 4) or None), ``T_est`` (list
        of (4, 4) or None), ``im_ids`` (N,).
    """
    from .groundtruth import GroundTruthWriter
    from .poses import PoseRow, write_poses
    from .recording import FORMAT, VERSION, pose_columns
    from .rig import Rig, RigCamera, save_rig
    from .camera import CameraIntrinsics
    from .se3 import pq_from_transform

    bop_dir = Path(bop_dir)
    out = Path(out)
    scenes = _find_scenes(bop_dir)
    root = bop_dir if not (bop_dir / "scene_camera.json").is_file() else bop_dir.parent.parent
    meta = json.loads((root / "vespro.json").read_text()) if (root / "vespro.json").is_file() else None
    obj_id = obj_id or (meta or {}).get("obj_id", OBJ_ID)
    cam_meta = {c["scene_id"]: c for c in (meta or {}).get("cameras", [])}
    if out.exists() and any(out.iterdir()):
        if not overwrite:
            raise FileExistsError(f"{out}: exists and is not empty")
        shutil.rmtree(out)
    out.mkdir(parents=True, exist_ok=True)

    sc_cam = {int(s.name): json.loads((s / "scene_camera.json").read_text()) for s in scenes}
    sc_gt = {int(s.name): json.loads((s / "scene_gt.json").read_text()) for s in scenes
             if (s / "scene_gt.json").is_file()}
    im_ids = sorted({int(k) for d in sc_cam.values() for k in d})
    n = len(im_ids)
    # Camera poses per scene and frame (None: no w2c given -> the world is the first such camera's frame).
    cams, T_wc = [], {}
    for s in scenes:
        sid = int(s.name)
        entries = sc_cam[sid]
        first = entries[str(im_ids[0])] if str(im_ids[0]) in entries else next(iter(entries.values()))
        K = np.array(first["cam_K"], dtype=float).reshape(3, 3)
        img0 = next((p for p in (_image_file(s, i) for i in im_ids) if p is not None), None)
        if "width" in first:
            w, h = int(first["width"]), int(first["height"])
        elif img0 is not None:
            h, w = _imread(img0).shape[:2]
        else:
            cj = json.loads((root / "camera.json").read_text())
            w, h = int(cj["width"]), int(cj["height"])
        intr = CameraIntrinsics(w, h, K, first.get("dist_coeffs", [0.0] * 5))
        poses = []
        for i in im_ids:
            e = entries.get(str(i), first)
            if "cam_R_w2c" in e:
                poses.append(invert_transform(_T_from_rt_mm(e["cam_R_w2c"], e["cam_t_w2c"])))
            else:
                poses.append(np.eye(4))
        poses = np.array(poses)
        T_wc[sid] = poses
        cm = cam_meta.get(sid, {})
        name = cm.get("name", f"cam{sid}")
        fixed = cm.get("mount") == "fixed" if cm else bool(np.allclose(poses, poses[0], atol=1e-12))
        if fixed:
            cams.append(RigCamera(name, intr, "fixed", T_world_camera=poses[0]))
        else:
            T_lc = np.array(cm["T_link_camera"]).reshape(4, 4) if "T_link_camera" in cm else np.eye(4)
            cams.append(RigCamera(name, intr, "eye_in_hand", link=cm.get("link", "camera"), T_link_camera=T_lc))
    rig = Rig(tuple(cams))
    sids = [int(s.name) for s in scenes]

    # Model back to metres.
    ply = root / "models" / f"obj_{obj_id:06d}.ply"
    model_m = load_model(ply, unit="mm", name=(meta or {}).get("object", f"obj_{obj_id:06d}"))
    import trimesh

    trimesh.Trimesh(model_m.vertices, model_m.triangles, process=False).export(str(out / "model.ply"))

    t = np.array(meta["t"]) if meta and len(meta.get("t", [])) == n else np.arange(n) / rate_hz
    rate = float(meta["rate_hz"]) if meta else float(rate_hz)
    (out / "meta.yaml").write_text(yaml.safe_dump(
        {"format": FORMAT, "version": VERSION, "rate_hz": rate, "model": "model.ply",
         "object": model_m.name, "bop_source": str(bop_dir), "bop_im_ids": im_ids}, sort_keys=False))
    save_rig(rig, out / "cameras.yaml")
    eih = [(k, c) for k, c in enumerate(rig) if not c.is_fixed]
    with open(out / "frames.csv", "w", newline="") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(["index", "t"] + [col for _, c in eih for col in pose_columns(c.name)])
        for j in range(n):
            w.writerow([str(j), f"{t[j]:.9f}"] + [f"{v:.9f}" for k, _ in eih
                                                    for v in pq_from_transform(T_wc[sids[k]][j])])
    for k, c in enumerate(rig):
        d = out / "frames" / c.name
        d.mkdir(parents=True)
        for j, i in enumerate(im_ids):
            src = _image_file(scenes[k], i)
            if src is None:
                continue
            if src.suffix == ".png":
                shutil.copyfile(src, d / f"{j:06d}.png")
            else:
                cv2.imwrite(str(d / f"{j:06d}.png"), _imread(src))

    # Ground truth: from the first scene that has the object in that image.
    T_true = None
    if sc_gt:
        T_true = np.full((n, 4, 4), np.nan)
        for j, i in enumerate(im_ids):
            for k, sid in enumerate(sids):
                hit = [g for g in sc_gt.get(sid, {}).get(str(i), []) if int(g["obj_id"]) == obj_id]
                if hit:
                    T_true[j] = T_wc[sid][j] @ _T_from_rt_mm(hit[0]["cam_R_m2c"], hit[0]["cam_t_m2c"])
                    break
        if np.all(np.isfinite(T_true)):
            with GroundTruthWriter(out) as gw:
                for j in range(n):
                    gw.write(j, float(t[j]), T_true[j])
    # Estimates: per image the best-scored row of the lowest scene id.
    if results is None:
        found = sorted(root.glob("*.csv"))
        results = found[0] if len(found) == 1 else None
    T_est = None
    if results is not None:
        rows = [r for r in read_results_csv(results) if r["obj_id"] == obj_id and r["scene_id"] in T_wc]
        pick = {}
        for r in sorted(rows, key=lambda r: (r["scene_id"], -r["score"])):
            pick.setdefault(r["im_id"], r)
        pos = {i: j for j, i in enumerate(im_ids)}
        T_est = [None] * n
        prow = []
        for j, i in enumerate(im_ids):
            r = pick.get(i)
            if r is not None and i in pos:
                T_est[j] = T_wc[r["scene_id"]][j] @ _T_from_rt_mm(r["R"], r["t"])
                prow.append(PoseRow(j, float(t[j]), "tracking", T_est[j], r["time"] * 1e3 if r["time"] >= 0 else None))
            else:
                prow.append(PoseRow(j, float(t[j]), "lost"))
        write_poses(out / "poses.csv", prow)
    return {"recording": out, "T_true": T_true, "T_est": T_est, "im_ids": np.array(im_ids)}
