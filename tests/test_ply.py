"""PLY through meshio (``sources.ply``): float64 bit for bit in ASCII and binary, bad files as one-line errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from core.errors import UserError
from sources.ply import COMMENT, ply_bytes, read_ply_xyz, write_ply

ROOT = Path(__file__).resolve().parents[1]
ORIGINAL = ROOT.parent / "shared" / "data" / "coloradar_maps" / "original" / "data" / "ply"

#: float64 values whose decimal parse is easy to get wrong: subnormals, extremes, -0, long mantissas
HARD = np.array([0.1, 0.075, -0.075, 1 / 3, 2.0 ** -1074, 5e-324, 2.2250738585072014e-308, 1.7976931348623157e308,
                 -0.0, 123456789.12345679, 0.15 * 7 + 0.075, 9007199254740993.0, 1e-300, -2.5e-17, 3.0])


def _tokens(path: Path) -> np.ndarray:
    """The vertex block's tokens parsed with Python's ``float`` (correctly rounded), as (N, 3)."""
    body = path.read_bytes().split(b"end_header\n", 1)[1]
    return np.array([float(t) for t in body.split()], dtype=np.float64).reshape(-1, 3)


@pytest.mark.skipif(not ORIGINAL.is_dir(), reason=f"the authors' PLY files are not at {ORIGINAL}")
@pytest.mark.parametrize("kind", ["radar", "lidar_filtered", "lidar"])
def test_authors_ascii_files_parse_bit_for_bit(kind: str) -> None:
    path = ORIGINAL / f"aspen_run0_{kind}.ply"
    got = read_ply_xyz(path)
    want = _tokens(path)
    assert got.dtype == np.float64 and got.shape == want.shape and len(got) > 1000
    assert np.array_equal(got.view(np.uint64), want.view(np.uint64))  # same bits, -0.0 included


@pytest.mark.parametrize("binary", [False, True])
def test_round_trip_is_exact(tmp_path: Path, binary: bool) -> None:
    rng = np.random.default_rng(0)
    pts = np.concatenate([HARD.reshape(-1, 3), rng.normal(size=(200, 3)) * 10.0 ** rng.integers(-8, 8, (200, 3))])
    path = write_ply(tmp_path / "a.ply", pts, binary=binary)
    got = read_ply_xyz(path)
    assert np.array_equal(got.view(np.uint64), pts.view(np.uint64))
    if not binary:
        assert np.array_equal(got.view(np.uint64), _tokens(path).view(np.uint64))


def test_ascii_notations_match_python_float(tmp_path: Path) -> None:
    """Open3D-style short decimals, exponents, signs and padding parse as ``float(token)``."""
    toks = ["-0.075", "0.225", "1e-5", "+3.5E+2", "0.30000000000000004", "-0", "7", "  2.5", "1.000000000000000111"]
    toks += ["0.1", "0.2", "0.3"]
    text = "ply\nformat ascii 1.0\ncomment Created by Open3D\nelement vertex 4\nproperty double x\nproperty double y\n"
    text += "property double z\nend_header\n" + "\n".join(" ".join(toks[i : i + 3]) for i in range(0, 12, 3)) + "\n"
    path = tmp_path / "n.ply"
    path.write_text(text)
    want = np.array([float(t) for t in toks]).reshape(4, 3)
    assert np.array_equal(read_ply_xyz(path).view(np.uint64), want.view(np.uint64))


@pytest.mark.parametrize("order", ["<", ">"])
def test_binary_either_byte_order_and_float32(tmp_path: Path, order: str) -> None:
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(50, 3))
    end = "little" if order == "<" else "big"
    for typ, dt in (("double", "f8"), ("float", "f4")):
        rec = np.empty(len(pts), [("x", order + dt), ("y", order + dt), ("z", order + dt), ("i", order + "f4")])
        rec["x"], rec["y"], rec["z"], rec["i"] = *pts.T, 1.0
        head = (f"ply\nformat binary_{end}_endian 1.0\nelement vertex {len(pts)}\nproperty {typ} x\nproperty {typ} y\n"
                f"property {typ} z\nproperty float intensity\nend_header\n")
        path = tmp_path / f"{typ}.ply"
        path.write_bytes(head.encode() + rec.tobytes())
        got = read_ply_xyz(path)
        assert got.dtype == np.float64
        assert np.array_equal(got, pts if dt == "f8" else pts.astype(np.float32).astype(np.float64))


def test_written_files_are_deterministic() -> None:
    pts = np.arange(12, dtype=np.float32).reshape(4, 3)
    a = ply_bytes(pts, {"log_odds": np.ones(4, np.float32)})
    assert a == ply_bytes(pts, {"log_odds": np.ones(4, np.float32)})
    header = a.split(b"end_header\n")[0].split(b"\n")
    assert COMMENT in header and not any(b"meshio v" in ln for ln in header)
    assert b"property float x" in header and b"property float log_odds" in header


def _ascii(tmp_path: Path, body: str, props: str = "property double x\nproperty double y\nproperty double z\n",
           n: int = 2) -> Path:
    path = tmp_path / "bad.ply"
    path.write_text(f"ply\nformat ascii 1.0\nelement vertex {n}\n{props}end_header\n{body}")
    return path


@pytest.mark.parametrize("case, expect", [
    ("missing", "missing"),
    ("not_ply", "does not start with 'ply'"),
    ("no_end_header", "no end_header"),
    ("short_ascii", "holds 1 of the 2 vertices"),
    ("ragged_ascii", "unreadable PLY"),
    ("text_token", "non-numeric or non-finite"),
    ("truncated_binary", "unreadable PLY"),
    ("no_z", "lacks vertex properties z"),
    ("xyz_not_first", "x, y, z must be the first vertex properties"),
    ("int_xyz", "must be floating point"),
    ("no_vertex", "has no 'vertex' element"),
    ("other_element", "only vertex and face are read"),
])
def test_bad_files_give_one_line_errors(tmp_path: Path, case: str, expect: str) -> None:
    xyz = "property double x\nproperty double y\nproperty double z\n"
    if case == "missing":
        path = tmp_path / "nothing.ply"
    elif case == "not_ply":
        path = tmp_path / "bad.ply"
        path.write_text("this is not a ply file\n")
    elif case == "no_end_header":
        path = tmp_path / "bad.ply"
        path.write_text("ply\nformat ascii 1.0\nelement vertex 2\n")
    elif case == "short_ascii":
        path = _ascii(tmp_path, "0 0 0\n")
    elif case == "ragged_ascii":
        path = _ascii(tmp_path, "0 0 0\n1 2\n")
    elif case == "text_token":
        path = _ascii(tmp_path, "0 0 0\n1 two 3\n")
    elif case == "truncated_binary":
        path = write_ply(tmp_path / "bad.ply", np.zeros((10, 3)))
        path.write_bytes(path.read_bytes()[:-7])
    elif case == "no_z":
        path = _ascii(tmp_path, "0 0\n1 1\n", "property double x\nproperty double y\n")
    elif case == "xyz_not_first":
        path = _ascii(tmp_path, "1 0 0 0\n1 1 1 1\n", "property float intensity\n" + xyz)
    elif case == "int_xyz":
        path = _ascii(tmp_path, "0 0 0\n1 1 1\n", xyz.replace("double", "int"))
    elif case == "no_vertex":
        path = tmp_path / "bad.ply"
        path.write_text("ply\nformat ascii 1.0\nelement face 0\nproperty list uchar int vertex_indices\nend_header\n")
    else:
        path = tmp_path / "bad.ply"
        path.write_text(f"ply\nformat ascii 1.0\nelement vertex 1\n{xyz}element edge 0\nproperty int vertex1\n"
                        "end_header\n0 0 0\n")
    with pytest.raises(UserError) as info:
        read_ply_xyz(path, "radar map")
    message = str(info.value)
    assert str(path) in message and expect in message and "\n" not in message, message


def test_no_plyfile_needed(tmp_path: Path) -> None:
    """plyfile (GPL-3.0) is not a dependency: reading and writing work with its import blocked."""
    import subprocess
    import sys

    code = ("import sys; sys.modules['plyfile'] = None\n"
            "import numpy as np; from pathlib import Path; from sources.ply import read_ply_xyz, write_ply\n"
            f"p = write_ply(Path({str(tmp_path / 'a.ply')!r}), np.ones((3, 3)), binary=False)\n"
            "assert read_ply_xyz(p).sum() == 9\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "plyfile" not in (ROOT / "pyproject.toml").read_text()
