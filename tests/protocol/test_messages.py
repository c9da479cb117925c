"""parse_request: every malformed request is refused with a message naming the problem."""

from __future__ import annotations

import math

import numpy as np
import pytest

from visfly_dist.errors import ProtocolError
from visfly_dist.protocol.cameras import CameraSpec
from visfly_dist.protocol.codec import decode, encode
from visfly_dist.protocol.messages import (
    MAX_AGENTS_PER_REQUEST, MAX_CAMERAS, REQUEST_TYPES, LoadScene, SampleSpawn, ScenePoses, StepRequest,
    parse_request,
)


def _poses(n: int = 2, dtype=np.float32) -> np.ndarray:
    p = np.zeros((n, 7), dtype=dtype)
    p[:, 2] = 1.0
    p[:, 3] = 1.0
    return p


def _step(**change) -> dict:
    msg = StepRequest((ScenePoses("s0", _poses()),)).to_message()
    msg.update(change)
    return msg


def _step_poses(poses) -> dict:
    n = len(poses) if hasattr(poses, "__len__") else 1
    return _step(keys=["s0"], counts=np.array([n], np.int32), poses=poses)


def _load(**change) -> dict:
    msg = LoadScene("s0", "gen:pillars", (CameraSpec(),)).to_message()
    msg.update(change)
    return msg


def _spawn(**change) -> dict:
    msg = SampleSpawn("s0", 4, 0.2, "uniform", (0, 0, 0), (1, 1, 1)).to_message()
    msg.update(change)
    return msg


def _without(msg: dict, key: str) -> dict:
    return {k: v for k, v in msg.items() if k != key}


def _nan_poses():
    p = _poses()
    p[1, 0] = np.nan
    return p


def _inf_poses():
    p = _poses()
    p[0, 4] = np.inf
    return p


def _nan_quat():
    p = _poses()
    p[1, 5] = np.nan
    return p


def _long_quat():
    p = _poses()
    p[0, 3] = 2.0
    return p


def _far_poses():
    p = _poses(dtype=np.float64)
    p[0, 1] = 1e7
    return p


MALFORMED = {
    "unknown type": ({"type": "launch_missiles"}, "unknown message type 'launch_missiles'; valid types: "
                     + ", ".join(REQUEST_TYPES)),
    "no type": ({}, "unknown message type None"),
    "unload without key": ({"type": "unload_scene"}, "missing field 'scene_key'"),
    "unload key not str": ({"type": "unload_scene", "scene_key": 3}, "'scene_key' must be str, got int"),
    "key with slash": ({"type": "unload_scene", "scene_key": "a/b"}, "scene_key='a/b' must be"),
    "key wildcard": ({"type": "unload_scene", "scene_key": "*"}, "scene_key='\\*' must be"),
    "key empty": ({"type": "unload_scene", "scene_key": ""}, "scene_key='' must be"),
    "load without source": (_without(_load(), "source"), "missing field 'source'"),
    "load empty source": (_load(source=""), "source must be a non-empty string"),
    "load huge source": (_load(source="x" * 5000), "source must be a non-empty string under 4096"),
    "load nul source": (_load(source="a\x00b"), "source must be a non-empty string"),
    "load cameras not list": (_load(cameras={"name": "d"}), "'cameras' must be list, got dict"),
    "load too many cameras": (_load(cameras=[CameraSpec(name=f"c{i}").to_dict() for i in range(MAX_CAMERAS + 1)]),
                              "17 cameras must be between 1 and the bound 16"),
    "load no camera": (_load(cameras=[]), "0 cameras must be between 1 and the bound 16"),
    "load bad camera kind": (_load(cameras=[{"name": "d", "kind": "lidar"}]), "kind='lidar' must be one of"),
    "load camera unknown key": (_load(cameras=[{"name": "d", "zoom": 2}]), "unknown keys \\['zoom'\\]"),
    "load camera not map": (_load(cameras=["depth"]), "camera spec must be a map"),
    "load absurd resolution": (_load(cameras=[{"name": "d", "width": 100000}]), "width=100000 must be an int"),
    "load duplicate cameras": (_load(cameras=[CameraSpec().to_dict(), CameraSpec().to_dict()]), "must be unique"),
    "load radius nan": (_load(drone_radius=math.nan), "drone_radius=nan must be finite"),
    "load radius negative": (_load(drone_radius=-1.0), "drone_radius=-1.0 must be finite and in"),
    "load radius bool": (_load(drone_radius=True), "'drone_radius' must be a number, got bool"),
    "load multi_agent not bool": (_load(multi_agent=1), "'multi_agent' must be bool, got int"),
    "step without keys": (_without(_step(), "keys"), "missing field 'keys'"),
    "step counts off": (_step(counts=np.array([5], np.int32)), "counts add up to 5 but poses has"),
    "step counts not one per key": (_step(keys=["s0", "s1"]), "one per key"),
    "step negative count": (_step(keys=["s0", "s1"], counts=np.array([2, -1], np.int32)), "non-negative"),
    "step keys not list": (_step(keys={"s0": 1}), "'keys' must be list, got dict"),
    "step counts as list": (_step(counts=[1]), "counts must be an integer array"),
    "step poses missing": (_without(_step(), "poses"), "poses must be an array, got NoneType"),
    "step poses as list": (_step_poses([[0, 0, 1, 1, 0, 0, 0]]), "poses must be an array, got list"),
    "step poses int dtype": (_step_poses(np.zeros((2, 7), np.int32)), "poses dtype int32 must be float32 or float64"),
    "step poses wrong shape": (_step_poses(np.zeros((2, 6), np.float32)), "poses shape \\(2, 6\\) must be \\(n, 7\\)"),
    "step poses 3d": (_step_poses(np.zeros((1, 2, 7), np.float32)), "poses shape \\(1, 2, 7\\)"),
    "step poses nan": (_step_poses(_nan_poses()), "NaN or infinite"),
    "step poses inf": (_step_poses(_inf_poses()), "NaN or infinite"),
    "step quaternion nan": (_step_poses(_nan_quat()), "NaN or infinite"),
    "step non-unit quaternion": (_step_poses(_long_quat()), "quaternions must be unit"),
    "step zero quaternion": (_step_poses(np.zeros((1, 7), np.float32)), "quaternions must be unit"),
    "step far position": (_step_poses(_far_poses()), "positions beyond 1e6 m"),
    "step absurd batch": (_step_poses(_poses(MAX_AGENTS_PER_REQUEST + 1)), "100001 poses exceed the bound 100000"),
    "step too many entries": (_step(keys=["s0"] * 1025, counts=np.zeros(1025, np.int32)), "1025 scene entries exceed"),
    "step bad key": (_step(keys=["../x"]), "scene_key='../x' must be"),
    "step radius missing": (_without(_step(), "search_radius"), "missing field 'search_radius'"),
    "step radius inf": (_step(search_radius=math.inf), "search_radius=inf must be finite"),
    "step radius str": (_step(search_radius="5"), "'search_radius' must be .*got str"),
    "spawn n zero": (_spawn(n=0), "n=0 must be in \\[1, 100000\\]"),
    "spawn n huge": (_spawn(n=10**9), "n=1000000000 must be in"),
    "spawn n float": (_spawn(n=2.5), "'n' must be int, got float"),
    "spawn bad distribution": (_spawn(distribution="cauchy"), "distribution='cauchy' must be 'uniform' or 'normal'"),
    "spawn a short": (_spawn(a=[0, 0]), "a must be a list of 3 numbers"),
    "spawn b nan": (_spawn(b=[1, math.nan, 1]), "b=nan must be finite"),
    "spawn a str": (_spawn(a=["0", 0, 0]), "a='0' must be a number, got str"),
    "spawn b none": (_spawn(b=None), "'b' must be list, got NoneType"),
    "spawn negative seed": (_spawn(seed=-1), "seed=-1 must be in \\[0, 2\\*\\*63 - 1\\]"),
    "spawn bool seed": (_spawn(seed=True), "'seed' must be int, got bool"),
    "spawn extra field": (_spawn(colour="red"), "unknown field\\(s\\) \\['colour'\\]"),
    "health extra field": ({"type": "health", "verbose": True}, "unknown field\\(s\\) \\['verbose'\\]"),
    "step render int": (_step(render=1), "'render' must be bool, got int"),
    "step query str": (_step(query="yes"), "'query' must be bool, got str"),
    "step extra field": (_step(scenes=[]), "step: unknown field\\(s\\) \\['scenes'\\]"),
    "key trailing newline": ({"type": "unload_scene", "scene_key": "s0\n"}, "scene_key='s0\\\\n' must be"),
    "key too long": ({"type": "unload_scene", "scene_key": "k" * 257}, "at most 256"),
    "load camera height bool": (_load(cameras=[{"name": "d", "height": True}]), "height=True must be an int"),
    "load camera hfov bool": (_load(cameras=[{"name": "d", "hfov_deg": False}]), "hfov_deg=False must be a number"),
    "load camera offset none": (_load(cameras=[{"name": "d", "offset": None}]), "offset=None must be 3 finite"),
    "load camera offset str": (_load(cameras=[{"name": "d", "offset": "abc"}]), "offset='abc' must be 3 finite"),
    "load camera rotation str": (_load(cameras=[{"name": "d", "rotation": "wxyz"}]), "rotation='wxyz' must be"),
    "load camera rotation bools": (_load(cameras=[{"name": "d", "rotation": [True, 0, 0, 0]}]), "rotation=.* must be"),
    "load camera near str": (_load(cameras=[{"name": "d", "near": "0.1"}]), "near='0.1'.* must be numbers"),
    "load camera name int": (_load(cameras=[{"name": 7}]), "name=7 must be a non-empty string"),
    "spawn low above high": (_spawn(a=[2, 0, 0]), "uniform low .* must not exceed high"),
    "spawn negative std": (_spawn(distribution="normal", b=[1, -1, 1]), "normal std .* must be non-negative"),
    "spawn clearance negative": (_spawn(clearance=-0.5), "clearance=-0.5 must be finite"),
    "spawn seed missing": (_without(_spawn(), "seed"), "missing field 'seed'"),
}


@pytest.mark.parametrize("name", list(MALFORMED))
def test_parse_request_rejects(name):
    msg, match = MALFORMED[name]
    with pytest.raises(ProtocolError, match=match):
        parse_request(msg)


@pytest.mark.parametrize("name", [n for n in MALFORMED if n.startswith("step poses")])
def test_malformed_poses_are_rejected_after_a_trip_through_the_codec(name):
    msg, match = MALFORMED[name]
    with pytest.raises(ProtocolError, match=match):
        parse_request(decode(encode(msg)))


def test_valid_requests_parse_to_float64_poses_and_normalised_cameras():
    req = parse_request(decode(encode(_step())))
    assert req.scenes[0].poses.dtype == np.float64 and req.search_radius == 5.0
    load = parse_request(_load(cameras=[{"name": "down", "rotation": [2.0, 0.0, 2.0, 0.0]}]))
    np.testing.assert_allclose(load.cameras[0].rotation, [math.sqrt(0.5), 0, math.sqrt(0.5), 0])


def test_an_image_segment_target_survives_the_codec_and_bad_ones_are_refused():
    from visfly_dist.protocol.image_segment import SegmentTarget

    target = SegmentTarget("visfly-img-run-w0-00ff", b"n" * 16, 4096, 7, {"depth": 64}, pid=1234, fd=17)
    step = StepRequest((ScenePoses("a", np.array([[0, 0, 1, 1, 0, 0, 0]], np.float32)),), image_segment=target)
    assert parse_request(decode(encode(step.to_message()))).image_segment == target
    assert parse_request(decode(encode(StepRequest(step.scenes).to_message()))).image_segment is None
    for bad, match in ((dict(extra=1), "must be a map of name, nonce, size, seq, blocks"),
                       (dict(blocks={"depth": 4096}), "offsets in"), (dict(size=True), "size=True"),
                       (dict(name="visfly-img-a\x00b"), "no path separators"), (dict(pid=0), "pid=0"),
                       (dict(fd=-1), "fd=-1"), (dict(fd="3"), "fd='3'"), (dict(pid=True), "pid=True")):
        message = step.to_message()
        message["image_segment"] = {**target.to_message(), **bad}
        with pytest.raises(ProtocolError, match=match):
            parse_request(decode(encode(message)))


@pytest.mark.parametrize("bad", ["", "k" * 257, "a\nb", "a/b", "s0\n", 7, None])
def test_the_one_pass_key_check_names_the_first_bad_entry(bad):
    keys = ["s0", "k" * 256, "a.b-c_d", bad, "s9"]
    msg = _step(keys=keys, counts=np.array([2, 0, 0, 0, 0], np.int32))
    with pytest.raises(ProtocolError, match=r"step\.keys\[3\]: (scene_key=|field .scene_key. must be str)"):
        parse_request(msg)


def test_a_parsed_step_keeps_the_wire_arrays_and_entry_views():
    poses = np.concatenate([_poses(2), _poses(3) + [1, 0, 0, 0, 0, 0, 0]])
    sent = StepRequest((ScenePoses("a", poses[:2], 1.5), ScenePoses("b", poses[2:2]), ScenePoses("a", poses[2:])))
    req = parse_request(decode(encode(sent.to_message())))
    assert req.keys == ("a", "b", "a") and req.counts.tolist() == [2, 0, 3] and req.times.tolist() == [1.5, 0, 0]
    assert req.poses.dtype == np.float64 and req.bounds() == [(0, 2), (2, 2), (2, 5)]
    np.testing.assert_array_equal(req.poses, poses)
    assert [(s.scene_key, len(s.poses), s.time) for s in req.scenes] == [("a", 2, 1.5), ("b", 0, 0.0), ("a", 3, 0.0)]
    with pytest.raises(AttributeError, match="immutable"):
        req.render = False
