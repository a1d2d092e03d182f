"""Damaged sessions: one SessionFormatError naming file and line, or skipped and counted with skip_bad."""

from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from appfusion.errors import AppFusionError, SessionFormatError
from appfusion.frame import Frame, Intrinsics, make_pose
from replay.session import (SessionReader, SessionWriter, parse_events, parse_groundtruth, parse_index,
                            parse_meta)

W, H = 32, 24
K = Intrinsics(W, H, 30.0, 30.0, 15.5, 11.5)
N = 5


@pytest.fixture(scope="module")
def good(tmp_path_factory):
    """A clean session: 5 frames of depth + IR + RGB, poses, pass events."""
    path = tmp_path_factory.mktemp("corrupt") / "good"
    rng = np.random.default_rng(1)
    with SessionWriter(path, device="sim", intrinsics={"depth": K, "ir": K, "rgb": K}) as w:
        w.event(0.0, "pass", "scan")
        for i in range(N):
            w.write(Frame(i, 1.0 + 0.1 * i, depth=np.full((H, W), 1.0 + i, np.float32),
                          ir=rng.integers(0, 1024, (H, W)).astype(np.float32),
                          rgb=rng.integers(0, 256, (H, W, 3)).astype(np.uint8), pose=make_pose(t=[i, 0, 0])))
    return path


@pytest.fixture
def sess(good, tmp_path):
    dst = tmp_path / "s"
    shutil.copytree(good, dst)
    return dst


def _lines(p):
    return p.read_text().splitlines(keepends=True)


def _data_line(p, k):
    """1-based file line number of the k-th (0-based) non-comment line of an index file."""
    nos = [i + 1 for i, ln in enumerate(_lines(p)) if ln.strip() and not ln.startswith("#")]
    return nos[k]


def _set_line(p, no, text):
    ls = _lines(p)
    ls[no - 1] = text
    p.write_text("".join(ls))


def _expect(sess, file, line, match, n_left=N - 1):
    """Strict open raises naming ``file:line``; skip_bad opens with one bad frame listed."""
    with pytest.raises(SessionFormatError, match=match) as ei:
        SessionReader(sess)
    e = ei.value
    assert e.path.endswith(file) and e.line == line
    assert f"{file}:{line}" in str(e) if line else file in str(e)
    r = SessionReader(sess, skip_bad=True)
    assert len(r) == n_left
    assert len(r.bad_frames) == 1 and r.bad_frames[0][0].endswith(file) and r.bad_frames[0][1] == line
    assert len(list(r)) == n_left
    return r


def test_clean_session_opens(sess):
    r = SessionReader(sess)
    assert len(r) == N and r.bad_frames == [] and r.dropped_lines == []


def test_missing_image(sess):
    (sess / "depth" / "1.200000.png").unlink()
    r = _expect(sess, "depth.txt", _data_line(sess / "depth.txt", 2), "1.200000.png, which does not exist")
    r.seek(0)
    assert [round(f.timestamp, 1) for f in r] == [1.0, 1.1, 1.3, 1.4]  # the whole frame is skipped


def test_truncated_png(sess):
    p = sess / "rgb" / "1.100000.png"
    p.write_bytes(p.read_bytes()[: p.stat().st_size // 2])
    _expect(sess, "rgb.txt", _data_line(sess / "rgb.txt", 1), "truncated PNG")


def test_empty_png(sess):
    (sess / "ir" / "1.000000.png").write_bytes(b"")
    _expect(sess, "ir.txt", _data_line(sess / "ir.txt", 0), "empty file")


def test_index_line_pointing_nowhere(sess):
    no = _data_line(sess / "depth.txt", 3)
    _set_line(sess / "depth.txt", no, "1.300000 depth/nothing.png\n")
    _expect(sess, "depth.txt", no, "does not exist")


def test_index_path_escaping_the_session(sess):
    no = _data_line(sess / "rgb.txt", 0)
    _set_line(sess / "rgb.txt", no, "1.000000 ../../etc/passwd\n")
    _expect(sess, "rgb.txt", no, "does not lie inside")


def test_unparsable_index_lines(sess):
    no = _data_line(sess / "ir.txt", 4)
    _set_line(sess / "ir.txt", no, "1.4x ir/1.400000.png\n")
    _expect(sess, "ir.txt", no, "not a number", n_left=N)  # timestamp unknown: only the IR is dropped
    _set_line(sess / "ir.txt", no, "just-one-field\n")
    with pytest.raises(SessionFormatError, match="expected 'timestamp path'"):
        SessionReader(sess)
    _set_line(sess / "ir.txt", no, "nan ir/1.400000.png\n")
    with pytest.raises(SessionFormatError, match="not finite"):
        SessionReader(sess)


def test_non_monotonic_timestamps(sess):
    ls = _lines(sess / "depth.txt")
    a, b = _data_line(sess / "depth.txt", 1), _data_line(sess / "depth.txt", 2)
    ls[a - 1], ls[b - 1] = ls[b - 1], ls[a - 1]
    (sess / "depth.txt").write_text("".join(ls))
    _expect(sess, "depth.txt", b, "not after the previous one")


def test_wrong_image_shape(sess):
    cv2.imwrite(str(sess / "depth" / "1.000000.png"), np.ones((H, W + 1), np.uint16))
    _expect(sess, "depth.txt", _data_line(sess / "depth.txt", 0), f"image is {W + 1}x{H}, meta.json says {W}x{H}")


def test_wrong_image_dtype(sess):
    cv2.imwrite(str(sess / "ir" / "1.100000.png"), np.ones((H, W), np.uint8))
    _expect(sess, "ir.txt", _data_line(sess / "ir.txt", 1), "8-bit grey, expected 16-bit grey")


def test_swapped_index_files(sess):
    d, r = (sess / "depth.txt").read_text(), (sess / "rgb.txt").read_text()
    (sess / "depth.txt").write_text(r)
    (sess / "rgb.txt").write_text(d)
    with pytest.raises(SessionFormatError, match=r"not in the depth/ folder \(swapped index files\?\)") as ei:
        SessionReader(sess)
    assert ei.value.path.endswith("depth.txt") and ei.value.line == 3


def test_swapped_image_files(sess):
    a, b = sess / "depth" / "1.200000.png", sess / "rgb" / "1.200000.png"
    da, db = a.read_bytes(), b.read_bytes()
    a.write_bytes(db)
    b.write_bytes(da)
    with pytest.raises(SessionFormatError, match="8-bit RGB, expected 16-bit grey") as ei:
        SessionReader(sess)
    assert ei.value.line == _data_line(sess / "depth.txt", 2)
    r = SessionReader(sess, skip_bad=True)
    assert len(r) == N - 1 and len(r.bad_frames) == 2  # both the depth and the rgb line are reported


def test_corrupt_png_data_found_when_decoding(sess):
    p = sess / "depth" / "1.300000.png"
    b = bytearray(p.read_bytes())
    b[60] ^= 0xFF  # inside the compressed data: the header and end chunk still look fine
    p.write_bytes(bytes(b))
    r = SessionReader(sess)
    assert len(r) == N
    with pytest.raises(SessionFormatError, match=r"cannot decode image .*depth.txt:\d+") as ei:
        list(r)
    assert ei.value.path.endswith("1.300000.png")
    r = SessionReader(sess, skip_bad=True)
    assert [round(f.timestamp, 1) for f in r] == [1.0, 1.1, 1.2, 1.4]
    assert len(r.bad_frames) == 1 and r.bad_frames[0][0].endswith("1.300000.png")


def test_half_written_last_line_is_dropped_not_an_error(sess):
    with open(sess / "depth.txt", "a") as f:
        f.write("1.500000 depth/1.5000")
    with open(sess / "events.txt", "a") as f:
        f.write("1.5 pass geo")
    r = SessionReader(sess)
    assert len(r) == N and r.bad_frames == []
    assert [(p.rsplit("/", 1)[-1], t) for p, _, t in r.dropped_lines] == [
        ("depth.txt", "1.500000 depth/1.5000"), ("events.txt", "1.5 pass geo")]


def test_missing_index_file(sess):
    (sess / "ir.txt").unlink()
    with pytest.raises(SessionFormatError, match="ir.txt: missing: meta.json declares a ir stream"):
        SessionReader(sess)


def test_bad_events_and_groundtruth_lines(sess):
    with open(sess / "events.txt", "a") as f:
        f.write("0.5 pass\n")
    with pytest.raises(SessionFormatError, match=r"events.txt:3: expected 'timestamp key value'"):
        SessionReader(sess)
    r = SessionReader(sess, skip_bad=True)
    assert len(r) == N and r.bad_frames[0][1] == 3
    (sess / "events.txt").write_text("2.0 pass a\n1.0 pass b\n")
    with pytest.raises(SessionFormatError, match="events.txt:2: event time 1.0 is before"):
        SessionReader(sess)
    (sess / "events.txt").write_text("1.0 emitter dim\n")
    with pytest.raises(SessionFormatError, match="events.txt:1: emitter event value"):
        SessionReader(sess)
    (sess / "events.txt").unlink()
    _set_line(sess / "groundtruth.txt", 4, "1.1 1 2 3 0 0 0 0\n")
    with pytest.raises(SessionFormatError, match="groundtruth.txt:4: quaternion norm 0 is far from 1"):
        SessionReader(sess)
    r = SessionReader(sess, skip_bad=True)
    assert r[1].pose is None and r[2].pose is not None


@pytest.mark.parametrize("content, match, line", [
    (None, "meta.json: missing: not an appfusion session", None),
    (b'{"format": "appfusion-session",\n "version": 1,,\n}', "not valid JSON", 2),
    (b"\xff\xfe\x00", "not UTF-8", None),
    (b"[1, 2]", "expected a JSON object, got list", None),
])
def test_meta_missing_or_unreadable(sess, content, match, line):
    if content is None:
        (sess / "meta.json").unlink()
    else:
        (sess / "meta.json").write_bytes(content)
    with pytest.raises(SessionFormatError, match=match) as ei:
        SessionReader(sess, skip_bad=True)  # a broken meta.json cannot be skipped
    assert ei.value.path.endswith("meta.json") and ei.value.line == line


@pytest.mark.parametrize("edit, match", [
    (lambda m: m.pop("streams"), "missing field 'streams'"),
    (lambda m: m.pop("device"), "missing field 'device'"),
    (lambda m: m["extrinsics"].pop("depth_to_rgb"), "missing field 'extrinsics.depth_to_rgb'"),
    (lambda m: m["streams"]["depth"].pop("units_per_m"), "missing field 'streams.depth.units_per_m'"),
    (lambda m: m["streams"]["rgb"]["intrinsics"].pop("fx"), "streams.rgb.intrinsics: .*'fx'"),
    (lambda m: m.update(format="tum"), "format is 'tum'"),
    (lambda m: m.update(version=2), "version 2 is newer"),
    (lambda m: m["streams"]["depth"].update(units_per_m=-5), "units_per_m must be a positive number"),
    (lambda m: m["streams"]["rgb"].update(encoding="jpeg"), "streams.rgb.encoding is 'jpeg'"),
    (lambda m: m["streams"].update(thermal={}), "unknown stream 'thermal'"),
    (lambda m: m["extrinsics"].update(depth_to_ir=[[1, 0], [0, 1]]), "expected a finite 4x4 matrix"),
    (lambda m: m.update(emitter_position_m=[0, 0]), "emitter_position_m must be 3 numbers"),
])
def test_meta_bad_fields(sess, edit, match):
    m = json.loads((sess / "meta.json").read_text())
    edit(m)
    (sess / "meta.json").write_text(json.dumps(m))
    with pytest.raises(SessionFormatError, match=match) as ei:
        SessionReader(sess)
    assert ei.value.path.endswith("meta.json")


# -- fuzzing: whatever the bytes, a parser returns or raises SessionFormatError, never anything else ---
_fuzz = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])

_line = st.one_of(
    st.text(max_size=30),
    st.builds(lambda t, p: f"{t} {p}", st.one_of(st.floats(allow_nan=True), st.integers(), st.text(max_size=5)),
              st.sampled_from(["depth/a.png", "rgb/b.png", "../x", "/abs", "depth/../../y", ".", "depth"])),
)
_index_text = st.lists(_line, max_size=8).map("\n".join)


@_fuzz
@given(data=st.one_of(st.binary(max_size=200), _index_text), skip=st.booleans())
def test_fuzz_index_parser(data, skip):
    try:
        entries, bad, dropped = parse_index(data, "depth.txt", stream="depth", skip_bad=skip)
    except SessionFormatError as e:
        assert not skip and "depth.txt:" in str(e)
        return
    ts = [t for _, _, t, _ in entries]
    assert ts == sorted(set(ts))
    assert all(rel.startswith("depth/") and ".." not in rel.split("/") for *_, rel in entries)


@_fuzz
@given(data=st.one_of(st.binary(max_size=200), st.lists(st.text(max_size=40), max_size=6).map("\n".join)),
       skip=st.booleans())
def test_fuzz_events_and_groundtruth_parsers(data, skip):
    for parse, name in ((parse_events, "events.txt"), (parse_groundtruth, "groundtruth.txt")):
        try:
            parse(data, name, skip_bad=skip)
        except SessionFormatError as e:
            assert not skip and name in str(e)


_json = st.recursive(st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
                     lambda c: st.lists(c, max_size=4) | st.dictionaries(st.text(max_size=8), c, max_size=4),
                     max_leaves=12)


@_fuzz
@given(path=st.lists(st.sampled_from(["streams", "depth", "rgb", "ir", "intrinsics", "extrinsics", "depth_to_ir",
                                      "fx", "width", "units_per_m", "encoding", "version", "format", "bits",
                                      "emitter_position_m", "dist", "extra"]), min_size=1, max_size=4),
       value=_json, delete=st.booleans())
def test_fuzz_meta_loader(good, path, value, delete):
    m = json.loads((good / "meta.json").read_text())
    node = m
    for key in path[:-1]:
        if not isinstance(node, dict) or key not in node:
            break
        node = node[key]
    else:
        if isinstance(node, dict):
            if delete:
                node.pop(path[-1], None)
            else:
                node[path[-1]] = value
    try:
        meta = parse_meta(json.dumps(m).encode(), "meta.json")
    except SessionFormatError as e:
        assert "meta.json" in str(e)
        return
    assert set(meta["_intrinsics"]) <= {"depth", "ir", "rgb"}


@_fuzz
@given(data=st.binary(max_size=300))
def test_fuzz_meta_bytes(data):
    with pytest.raises(SessionFormatError):
        parse_meta(data, "meta.json")


def test_errors_are_appfusion_errors():
    assert issubclass(SessionFormatError, AppFusionError)


def test_check_images_false_defers_to_reading(sess):
    p = sess / "rgb" / "1.100000.png"
    p.write_bytes(p.read_bytes()[:100])
    r = SessionReader(sess, check_images=False)
    assert len(r) == N and r[0].rgb is not None
    with pytest.raises(SessionFormatError, match=r"1.100000.png: cannot decode image \(100 bytes\) \(from .*rgb.txt:4\)"):
        r[1]
