"""The whole cell end to end (lockstep: deterministic on any machine).

Plant, pose server and servo run on one simulated clock with the same code as
the real-time demo; the part is acquired from the images alone (automatic
initialisation), poses go over the real TCP link, and the figures come from the
plant's ground-truth log.
"""

import json

import pytest

pytest.importorskip("vespro.init", reason="automatic initialisation is needed to acquire the part")

from cellsim.demo import DemoConfig, run_demo  # noqa: E402

WATCHDOG_S = 3 / 26  # the servo's default: no valid pose for 3 frame periods


@pytest.mark.slow
def test_lockstep_demo_acquires_approaches_and_follows(tmp_path):
    s = run_demo(DemoConfig(out=tmp_path, cameras="fixed", duration=8.0, lockstep=True, video=False), log=lambda m: None)
    e, te, sv = s["estimation"], s["tracking_error"], s["servo"]
    # Measured on a 20 s run: acquired at 0.04 s; estimation 1.2 mm / 1.3 deg RMSE; stand-off reached
    # at 3.6 s; following RMSE 5.4 mm (most of it the 1.3 deg orientation error on the 0.15 m lever arm).
    assert e["acquired"] and e["time_to_first_track_s"] < 1.0
    assert e["position_rmse_mm"] < 3.0 and e["orientation_rmse_deg"] < 3.0
    assert te["reached_standoff"] and te["moving_rmse_mm"] < 10.0
    assert sv["controlled_stops"] == 0 and sv["status_ticks"]["FAULT"] == 0  # nominal: no watchdog stop
    assert sum(sv["link"]["rejected"].values()) == 0 and sv["link"]["seq_gaps"] == 0
    assert (tmp_path / "vision" / "recording" / "groundtruth.csv").exists()  # replayable with vespro eval
    assert json.loads((tmp_path / "summary.json").read_text())["estimation"]["acquired"]


@pytest.mark.slow
def test_killed_pose_server_gives_a_controlled_stop_and_is_reported(tmp_path):
    s = run_demo(DemoConfig(out=tmp_path, cameras="fixed", duration=7.0, lockstep=True, video=False,
                            kill_server_at=5.0), log=lambda m: None)
    assert s["events"] and s["events"][0]["event"] == "pose server killed"
    sv = s["servo"]
    assert sv["status_ticks"]["TRACKING"] > 0  # it was following before
    assert sv["controlled_stops"] >= 1 and sv["status_ticks"]["FAULT"] == 0
    # The stop starts within the watchdog time after the last pose (plus one tick), not later.
    kill_t = s["events"][0]["t_s"]
    assert kill_t <= sv["first_stop_s"] <= kill_t + WATCHDOG_S + 0.05, (kill_t, sv["first_stop_s"])


@pytest.mark.slow
def test_real_time_demo_survives_a_killed_pose_server(tmp_path):
    # The multi-process path: plant, pose server and servo as their own processes on the
    # wall clock, a real TCP link. SIGKILL the pose server: the demo must report it and end
    # by itself (no hang), the servo must never fault, and if it was following when the
    # stream stopped its stop must start within the watchdog time (generous margin: a shared
    # CI machine delays processes, this is not a timing benchmark). A stop before the kill
    # (the stream late on a loaded machine) is the watchdog doing its job, not a failure: what
    # is checked is that a servo still following at the kill stops within the watchdog time.
    s = run_demo(DemoConfig(out=tmp_path, cameras="fixed", duration=9.0, video=False, kill_server_at=6.0),
                 log=lambda m: None)
    assert any(e.get("event") == "pose server killed" for e in s["events"])
    assert not any(e.get("event") in ("timeout", "killed after timeout") for e in s["events"]), s["events"]
    sv = s["servo"]
    assert sv["status_ticks"]["FAULT"] == 0 and sv["ticks"] > 0
    kill_t = next(e["t_s"] for e in s["events"] if e.get("event") == "pose server killed")
    changes = sv["status_changes"]
    assert changes and changes[0][0] <= kill_t
    at_kill = [name for t, name in changes if t <= kill_t - 0.5]
    if at_kill and at_kill[-1] == "TRACKING":  # following half a second before the kill
        stops = [t for t, name in changes if name in ("STOPPING", "STOPPED") and t > kill_t - 0.5]
        assert stops and stops[0] <= kill_t + WATCHDOG_S + 0.5, (kill_t, changes)
        assert sv["controlled_stops"] >= 1
    assert (tmp_path / "summary.json").exists()


def test_eye_in_hand_cell_waits_where_its_camera_sees_the_belt_entry():
    """With only the arm's camera, the arm starts at a search pose: the part entering on the belt
    is in view, seen obliquely (from home the camera looks at the floor)."""
    import numpy as np

    from vespro.camera import project_points
    from cellsim.demo import search_q0
    from vespro.rig import load_rig
    from vespro.sim.rigs import CAMERAS_DIR

    assert search_q0("hybrid") is None and search_q0("fixed") is None
    q0 = search_q0("eye-in-hand")
    cam = load_rig(CAMERAS_DIR / "hand.yaml").cameras[0]

    def view(q):
        import mujoco

        from vespro.sim.scene import CELL_XML

        m = mujoco.MjModel.from_xml_path(str(CELL_XML))
        d = mujoco.MjData(m)
        d.qpos[:6] = q
        mujoco.mj_forward(m, d)
        b = m.body(cam.link).id
        T_wl = np.eye(4)
        T_wl[:3, :3] = d.xmat[b].reshape(3, 3)
        T_wl[:3, 3] = d.xpos[b]
        return T_wl @ cam.T_link_camera

    for q, seen in ((q0, True), (np.array([0.0, -0.6, 0.9, 0.0, 1.2, 0.0]), False)):
        T_wc = view(q)
        parts = np.array([[0.90, y, 0.52] for y in (-0.30, -0.15, 0.0)])  # the part's path into the cell
        T_cw = np.linalg.inv(T_wc)
        pc = parts @ T_cw[:3, :3].T + T_cw[:3, 3]
        uv, _ = project_points(cam.intrinsics, T_cw, parts)
        inside = (pc[:, 2] > 0) & (uv[:, 0] > 0) & (uv[:, 0] < 640) & (uv[:, 1] > 0) & (uv[:, 1] < 480)
        assert inside.all() == seen
    tilt = np.degrees(np.arccos(-view(q0)[2, 2]))  # optical axis from straight down
    assert 20 < tilt < 70
