"""Per-frame time against ViSP's model-based tracker, same frames, same start pose, one run.

ViSP (Debian ``libvisp-dev``, 3.5) runs through a small C++ harness
(``bench/visp_harness.cpp``, compiled here with g++ and ``pkg-config visp`` into the
cache folder): ``vpMbGenericTracker`` with moving edges alone, and with moving edges
and KLT points. Ours: :class:`vespro.tracker.Tracker` with its default configuration.
Both start from the same pose at frame 0 and track every later frame; only the
tracking call is timed on either side (image reading is not), by default as the
tracking thread's CPU time (``--clock wall``: wall time), ViSP with one OpenMP thread.

Sequences:

- ``cube``: ViSP's own real sequence (``visp-images-data``, ``mbt/cube``: one camera,
  218 grey frames, its ``.cao`` model, camera file and start pose ``cube.0.pos``);
- ``box`` and ``lblock``: the tracker bench's recordings of the part on the conveyor
  seen by two fixed cameras (640x480 grey, 0.5 px noise; ``bench/tracker.py``), with
  ``.cao`` models and camera files written from our mesh and rig, ViSP's moving-edge
  settings those of its cube example, and its scanline visibility test for the
  non-convex L-block.

Printed per sequence and tracker: the frames it did not track (ours: not ``tracking``;
ViSP: its tracking call failed, the pose kept), median and p99 of the per-frame time, ours / ViSP
(medians), the median pose distance between ours and that tracker (ADD over the part's
symmetries, mm: ours picks one of a symmetric part's equivalent poses by a rule) and,
where the recording has ground truth, each tracker's ADD RMSE against it.

With ``libvisp-dev`` absent the bench prints one line and exits.

Usage: ``python bench/vs_visp.py [--frames 78] [--cache out/bench_visp] [--only cube,box,lblock]``
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402
from _cpuclock import tracker_clock  # noqa: E402
from _table import print_table  # noqa: E402
from _visp_data import VISP_MBT, Sequence, visp_cube, write_cao, write_tracker_xml  # noqa: E402
from tracker import bench_recording  # noqa: E402

from vespro.groundtruth import read_groundtruth  # noqa: E402
from vespro.metrics import add_sym, discrete_symmetries  # noqa: E402
from vespro.model import load_model  # noqa: E402
from vespro.recording import Recording  # noqa: E402
from vespro.se3 import invert_transform  # noqa: E402
from vespro.tracker import InitResult, Tracker  # noqa: E402

HARNESS = Path(__file__).resolve().parent / "visp_harness.cpp"


def build_harness(cache: Path) -> Path | None:
    """The compiled harness (rebuilt when its source is newer), or None without libvisp-dev."""
    if shutil.which("pkg-config") is None or shutil.which("g++") is None or \
            subprocess.run(["pkg-config", "--exists", "visp"]).returncode != 0:
        return None
    exe = cache / "visp_harness"
    if exe.exists() and exe.stat().st_mtime >= HARNESS.stat().st_mtime:
        return exe
    cache.mkdir(parents=True, exist_ok=True)
    flags = subprocess.run(["pkg-config", "--cflags", "--libs", "visp"], capture_output=True, text=True,
                           check=True).stdout.split()
    subprocess.run(["g++", "-O2", "-o", str(exe), str(HARNESS), *flags], check=True)
    return exe


def _matrix(T: np.ndarray) -> str:
    return " ".join(f"{v:.12g}" for v in np.asarray(T, float).ravel())


def run_visp(exe: Path, work: Path, mode: str, cao: Path, cams: list, T_c0_o: np.ndarray, n: int,
             scanline: bool, kind: str) -> tuple[np.ndarray, np.ndarray, int]:
    """ViSP's per-frame times (ms, ``kind`` "cpu" or "wall"; frame 0 is the start: 0), poses
    cMo of camera 0, (n, 4, 4), and the number of frames its tracking call failed on (it
    then keeps its last pose).

    ``cams``: (name, tracker xml, image paths, T_cam0_cam) per camera, camera 0 first."""
    lines = [f"mode {mode}", f"scanline {int(scanline)}", f"model {cao}", f"frames {n}"]
    for name, xml, paths, T_0k in cams:
        lst = work / f"{name}.txt"
        lst.write_text("\n".join(str(p) for p in paths[:n]) + "\n")
        lines.append(f"camera {name} {xml} {lst} {_matrix(T_0k)}")
    lines.append(f"pose {_matrix(T_c0_o)}")
    job, out = work / f"job_{mode}.txt", work / f"out_{mode}.txt"
    job.write_text("\n".join(lines) + "\n")
    r = subprocess.run([str(exe), str(job), str(out)], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"visp_harness failed: {r.stderr.strip()}")
    a = np.loadtxt(out, ndmin=2)
    failed = next((int(ln.split()[1]) for ln in r.stderr.splitlines() if ln.endswith("frames failed")), 0)
    return a[:, 1 if kind == "cpu" else 0], a[:, 2:].reshape(-1, 4, 4), failed


def run_ours(seq: Sequence, kind: str) -> tuple[np.ndarray, np.ndarray, list]:
    """Our per-frame times (ms, by ``kind``), poses T_world_object (NaN where not tracking) and statuses."""
    tr = Tracker(seq.rig, seq.model)
    times, poses, status = [], [], []
    for i in range(len(seq)):
        fs = seq.frameset(i)  # images read here, outside the timed call
        if i == 0:
            tr.start(InitResult(seq.T_start), fs.t_ns)
        with tracker_clock(kind):
            o = tr.process(fs)
        times.append(o.time_ms)
        poses.append(o.T_world_object if o.T_world_object is not None else np.full((4, 4), np.nan))
        status.append(o.status)
    return np.array(times), np.array(poses), status


class _RecordingSequence(Sequence):
    """A recording of ours as a :class:`Sequence` (its fixed cameras only)."""

    def __init__(self, rec: Recording, T_start: np.ndarray):
        self.rec = rec
        super().__init__(rec.rig, load_model(rec.model_path, name=rec.object_name), [], T_start)

    def frameset(self, i):
        return self.rec.frameset(i)

    def __len__(self):
        return len(self.rec)


def sequences(args):
    """(name, Sequence, .cao, ViSP camera list, scanline, ground truth T_world_object or None)."""
    out = []
    work = args.cache / "work"
    if "cube" in args.only:
        seq = visp_cube()
        if seq is None:
            print("vs_visp: visp-images-data is not installed (apt-get install visp-images-data); cube skipped")
        else:
            cams = [("cam0", VISP_MBT / "cube.xml", seq.frames, np.eye(4))]
            out.append(("cube (ViSP, real, 1 cam)", seq, VISP_MBT / "cube.cao", cams, False, None))
    for obj in ("box", "lblock"):
        if obj not in args.only:
            continue
        path = bench_recording(args.cache.parent / "bench_tracker", obj, "fixed2", args.frames, mono=True)
        rec = Recording(path)
        _, _, T = read_groundtruth(path)
        seq = _RecordingSequence(rec, T[0])
        d = work / obj
        d.mkdir(parents=True, exist_ok=True)
        cao = d / f"{obj}.cao"
        write_cao(seq.model, cao)
        T_w0 = rec.rig.cameras[0].T_world_camera
        cams = []
        for c in rec.rig:
            xml = d / f"{c.name}.xml"
            write_tracker_xml(c.intrinsics, xml)
            paths = [rec.image_path(c.name, i).resolve() for i in range(len(rec))]
            cams.append((c.name, xml, paths, invert_transform(T_w0) @ c.T_world_camera))
        out.append((f"{obj} (ours, sim, 2 cams)", seq, cao, cams, obj == "lblock", T))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=78, help="frames of our recordings (the cube has 218)")
    ap.add_argument("--cache", type=Path, default=Path("out/bench_visp"))
    ap.add_argument("--only", default="cube,box,lblock", help="comma-separated: cube, box, lblock")
    ap.add_argument("--clock", choices=["cpu", "wall"], default="cpu",
                    help="per-frame time as the tracking thread's CPU time (a busy machine's preemptions "
                         "left out; see bench/_cpuclock.py) or as wall time")
    args = ap.parse_args()
    args.only = set(args.only.split(","))
    os.environ.setdefault("OMP_NUM_THREADS", "1")  # ViSP's OpenMP: one thread, as ours
    exe = build_harness(args.cache)
    if exe is None:
        print("vs_visp: libvisp-dev not found (pkg-config visp); install it with "
              "apt-get install --no-install-recommends libvisp-dev; skipped")
        return
    rows = []
    for name, seq, cao, cams, scanline, T_true in sequences(args):
        n = len(seq)
        T_w0 = seq.rig.cameras[0].T_world_camera
        sym = discrete_symmetries(seq.model.vertices)
        V = seq.model.vertices
        t_ours, P_ours, st = run_ours(seq, args.clock)
        res = {"ours": (t_ours[1:], P_ours, f"{n - 1 - sum(x == 'tracking' for x in st[1:])}")}
        work = args.cache / "work" / name.split()[0]
        work.mkdir(parents=True, exist_ok=True)
        for mode, label in (("edges", "ViSP edges"), ("klt", "ViSP edges+KLT")):
            t_v, cMo, failed = run_visp(exe, work, mode, cao, cams, invert_transform(T_w0) @ seq.T_start, n, scanline,
                                args.clock)
            res[label] = (t_v[1:], np.array([T_w0 @ T for T in cMo]), str(failed))
        for label, (t, P, lost) in res.items():
            agree = [add_sym(P_ours[i], P[i], V, sym) for i in range(1, n) if np.all(np.isfinite(P_ours[i]))]
            err = ""
            if T_true is not None:
                e = [add_sym(P[i], T_true[i], V, sym) if np.all(np.isfinite(P[i])) else np.nan for i in range(1, n)]
                err = f"{np.sqrt(np.nanmean(np.square(e))) * 1e3:.2f}"
            ratio = "" if label == "ours" else f"{np.median(t_ours[1:]) / np.median(t):.2f}"
            rows.append([name, label, lost, float(np.median(t)), float(np.percentile(t, 99)), ratio,
                         "" if label == "ours" else f"{np.median(agree) * 1e3:.2f}", err])
    print_table(["sequence", "tracker", "frames not tracked", "median ms", "p99 ms", "ours/this", "vs ours mm",
                 "ADD RMSE mm"], rows,
                title=f"Per-frame tracking time ({args.clock}), ours against ViSP's vpMbGenericTracker "
                      f"(same frames, same start)")


if __name__ == "__main__":
    main()
