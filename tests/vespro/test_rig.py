import numpy as np
import pytest
import yaml

from vespro.rig import RigError, load_rig, save_rig


def write(tmp_path, data):
    p = tmp_path / "cameras.yaml"
    p.write_text(yaml.safe_dump(data) if not isinstance(data, str) else data)
    return p


def good():
    return {
        "cameras": [
            {
                "name": "cam0", "image_width": 640, "image_height": 480,
                "camera_matrix": [500, 0, 319.5, 0, 500, 239.5, 0, 0, 1],
                "distortion_model": "plumb_bob", "distortion_coefficients": [0.1, 0, 0, 0, 0],
                "mount": "fixed", "T_world_camera": [1, 2, 3, 1, 0, 0, 0],
            },
            {
                "name": "hand", "image_width": 320, "image_height": 240,
                "camera_matrix": [250, 0, 159.5, 0, 250, 119.5, 0, 0, 1],
                "mount": "eye_in_hand", "link": "flange", "T_link_camera": [0, 0, 0.1, 0, 0, 1, 0],
            },
        ]
    }


def test_roundtrip(tmp_path):
    rig = load_rig(write(tmp_path, good()))
    out = tmp_path / "again.yaml"
    save_rig(rig, out)
    rig2 = load_rig(out)
    assert rig2.names == ["cam0", "hand"]
    for a, b in zip(rig, rig2):
        np.testing.assert_allclose(a.intrinsics.K, b.intrinsics.K)
        np.testing.assert_allclose(a.intrinsics.dist, b.intrinsics.dist)
    np.testing.assert_allclose(rig2["cam0"].T_world_camera[:3, 3], [1, 2, 3])
    assert rig2["hand"].link == "flange"


def test_example_rig_loads(example_box2):
    rig = load_rig(example_box2 / "cameras.yaml")
    assert rig.names == ["cam0", "cam1"] and all(c.is_fixed for c in rig)


@pytest.mark.parametrize(
    "mutate, match",
    [
        (lambda d: d["cameras"][0].pop("camera_matrix"), "cam0.*camera_matrix"),
        (lambda d: d["cameras"][0].update(camera_matrix=[1, 2, 3]), "camera_matrix: expected 9"),
        (lambda d: d["cameras"][0].update(T_world_camera=[0, 0, 0, 2, 0, 0, 0]), "T_world_camera.*unit norm"),
        (lambda d: d["cameras"][1].pop("link"), "hand.*link"),
        (lambda d: d["cameras"][0].update(mount="ceiling"), "mount"),
        (lambda d: d["cameras"][0].update(image_width=-3), "image_width"),
        (lambda d: d["cameras"][0].update(distortion_model="fisheye"), "distortion_model"),
        (lambda d: d["cameras"][1].update(name="cam0"), "unique"),
        (lambda d: d.pop("cameras"), "cameras"),
    ],
)
def test_malformed_rig_names_file_and_field(tmp_path, mutate, match):
    d = good()
    mutate(d)
    p = write(tmp_path, d)
    with pytest.raises(RigError, match=match) as e:
        load_rig(p)
    assert "cameras.yaml" in str(e.value)


def test_not_yaml_and_missing(tmp_path):
    with pytest.raises(RigError, match="not valid YAML"):
        load_rig(write(tmp_path, "cameras: [\n  - {"))
    with pytest.raises(RigError, match="not found"):
        load_rig(tmp_path / "nope.yaml")
