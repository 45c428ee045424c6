"""The ``tyndall`` command installed with the Python package, run as a subprocess."""

from __future__ import annotations

import json
import struct
import subprocess
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import OpenEXR
import tyndall

SceneDict = dict[str, Any]
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# PNG colour type → samples per pixel.
PNG_CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}


def run(exe: Path, *args: str | Path, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [str(exe), *map(str, args)], cwd=cwd, capture_output=True, text=True, timeout=120, check=False
    )


def png_size(data: bytes) -> tuple[int, int]:
    """Decodes a PNG's chunk structure with the standard library; returns (width, height).

    Checks the signature, every chunk's CRC, IHDR first and IEND last, and that the
    inflated IDAT stream holds exactly one filter byte plus one row of samples per row.
    """
    assert data[:8] == PNG_SIGNATURE
    pos, chunks = 8, []
    while pos < len(data):
        (length,) = struct.unpack(">I", data[pos : pos + 4])
        kind = data[pos + 4 : pos + 8]
        body = data[pos + 8 : pos + 8 + length]
        (crc,) = struct.unpack(">I", data[pos + 8 + length : pos + 12 + length])
        assert zlib.crc32(kind + body) == crc, kind
        chunks.append((kind, body))
        pos += 12 + length
    assert pos == len(data)
    assert chunks[0][0] == b"IHDR" and chunks[-1][0] == b"IEND"
    width, height, bit_depth, colour_type, _, _, interlace = struct.unpack(">IIBBBBB", chunks[0][1])
    assert interlace == 0
    raw = zlib.decompress(b"".join(body for kind, body in chunks if kind == b"IDAT"))
    row_bytes = (width * PNG_CHANNELS[colour_type] * bit_depth + 7) // 8
    assert len(raw) == height * (1 + row_bytes)
    assert all(raw[r * (1 + row_bytes)] <= 4 for r in range(height))  # valid filter types
    return width, height


def test_help_exits_zero(tyndall_exe: Path) -> None:
    top = run(tyndall_exe, "--help")
    assert top.returncode == 0, top.stderr
    for command in ("render", "demo", "schema", "bench"):
        assert command in top.stdout
    sub = run(tyndall_exe, "render", "--help")
    assert sub.returncode == 0, sub.stderr
    for option in ("--out", "--report", "--preview", "--tolerance", "--threads", "--quiet"):
        assert option in sub.stdout


def test_version(tyndall_exe: Path) -> None:
    r = run(tyndall_exe, "--version")
    assert r.returncode == 0
    assert tyndall.__version__ in r.stdout


def test_usage_error_exits_two(tyndall_exe: Path) -> None:
    r = run(tyndall_exe, "render")
    assert r.returncode == 2
    assert "--out" in r.stderr
    assert run(tyndall_exe, "no-such-command").returncode == 2


def test_render_example_writes_exr_and_report(tyndall_exe: Path, repo_root: Path, tmp_path: Path) -> None:
    scene = repo_root / "examples" / "valley_height_fog.json"
    out, report_path = tmp_path / "OUT.exr", tmp_path / "R.json"
    r = run(
        tyndall_exe,
        "render",
        scene,
        "--out",
        "OUT.exr",
        "--report",
        "R.json",
        "--tolerance",
        "1e-5",
        "--quiet",
        cwd=tmp_path,
    )
    assert r.returncode == 0, r.stderr
    assert r.stderr == ""  # --quiet: no progress bar
    assert "OUT.exr" in r.stdout
    assert sorted(p.name for p in tmp_path.iterdir()) == ["OUT.exr", "R.json"]
    report = json.loads(report_path.read_text())
    assert report["error"]["tolerance"] == 1e-5
    width, height = json.loads(scene.read_text())["camera"]["resolution"]
    assert report["resolution"] == [width, height]
    exr = OpenEXR.File(str(out), separate_channels=True)
    channels = exr.parts[0].channels
    assert {"inscatter.R", "transmittance.G", "depth.Z"} <= set(channels)
    assert channels["depth.Z"].pixels.shape == (height, width)


def test_render_default_report_path(tyndall_exe: Path, small_scene: Callable[..., SceneDict], tmp_path: Path) -> None:
    scene = tmp_path / "scene.json"
    scene.write_text(json.dumps(small_scene()))
    out_dir = tmp_path / "out"
    r = run(tyndall_exe, "render", scene, "--out", out_dir / "OUT.exr", "--quiet")
    assert r.returncode == 0, r.stderr
    assert sorted(p.name for p in out_dir.iterdir()) == ["OUT.exr", "OUT.report.json"]
    report = json.loads((out_dir / "OUT.report.json").read_text())
    assert report["error"]["tolerance"] == 1e-4  # the format's default, no --tolerance given
    assert report["resolution"] == small_scene()["camera"]["resolution"]


def test_render_bad_scene_exits_one_and_writes_nothing(
    tyndall_exe: Path, small_scene: Callable[..., SceneDict], tmp_path: Path
) -> None:
    bad = small_scene(media=[{"type": "homogeneous", "scattering": [0.01, -0.02, 0.03]}])
    scene = tmp_path / "bad_scene.json"
    scene.write_text(json.dumps(bad))
    r = run(tyndall_exe, "render", scene, "--out", tmp_path / "OUT.exr", "--preview", tmp_path / "P.png", "--quiet")
    assert r.returncode == 1
    assert str(scene) in r.stderr
    assert "media[0].scattering[1]" in r.stderr
    assert "error" in r.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad_scene.json"]


def test_render_missing_scene_file_exits_one(tyndall_exe: Path, tmp_path: Path) -> None:
    missing = tmp_path / "missing.json"
    r = run(tyndall_exe, "render", missing, "--out", tmp_path / "OUT.exr", "--quiet")
    assert r.returncode == 1
    assert str(missing) in r.stderr
    assert not (tmp_path / "OUT.exr").exists()


def test_demo_writes_exr_png_and_report_per_example(tyndall_exe: Path, repo_root: Path, tmp_path: Path) -> None:
    out_dir = tmp_path / "demo"
    r = run(tyndall_exe, "demo", "--out-dir", out_dir, "--quiet")
    assert r.returncode == 0, r.stderr
    examples = sorted((repo_root / "examples").glob("*.json"))
    stems = [p.stem for p in examples] + ["sky_atmosphere"]
    expected = sorted(f"{stem}{ext}" for stem in stems for ext in (".exr", ".png", ".report.json"))
    assert sorted(p.name for p in out_dir.iterdir()) == expected
    sky = json.loads((out_dir / "sky_atmosphere.report.json").read_text())
    assert sky["resolution"] == [1024, 512] and sky["sun_lamp"]["strength_w_m2"] > 0
    assert png_size((out_dir / "sky_atmosphere.png").read_bytes()) == (1024, 512)
    for example in examples:
        width, height = json.loads(example.read_text())["camera"]["resolution"]
        assert png_size((out_dir / f"{example.stem}.png").read_bytes()) == (width, height)
        report = json.loads((out_dir / f"{example.stem}.report.json").read_text())
        assert report["resolution"] == [width, height]
        header = OpenEXR.File(str(out_dir / f"{example.stem}.exr"), header_only=True).parts[0].header
        assert [list(corner) for corner in header["dataWindow"]] == [[0, 0], [width - 1, height - 1]]


def test_schema_is_json_with_camera_and_media(tyndall_exe: Path) -> None:
    r = run(tyndall_exe, "schema")
    assert r.returncode == 0, r.stderr
    schema = json.loads(r.stdout)
    assert {"camera", "media", "lights", "meshes", "output", "version"} <= set(schema["properties"])
    assert set(schema["required"]) == {"version", "camera"}
    assert schema == json.loads(tyndall.scene_schema())


def test_output_paths_are_checked_before_the_render(
    tyndall_exe: Path, small_scene: Callable[..., SceneDict], tmp_path: Path
) -> None:
    """`--report` into a missing folder failed after the EXR was written, naming a temp
    file; `--out` naming a folder said "Not a directory"; `--out x.png` wrote an EXR
    under that name. The paths are now checked (and folders made) before the render."""
    scene = tmp_path / "s.json"
    scene.write_text(json.dumps(small_scene()))
    report = tmp_path / "b" / "c" / "r.json"
    out, preview = tmp_path / "a" / "o.exr", tmp_path / "d" / "p.png"
    r = run(tyndall_exe, "render", scene, "--out", out, "--report", report, "--preview", preview, "--quiet")
    assert r.returncode == 0, r.stderr
    assert json.loads((tmp_path / "b" / "c" / "r.json").read_text())["resolution"]
    assert png_size((tmp_path / "d" / "p.png").read_bytes())[0] > 0
    folder = tmp_path / "folder"
    folder.mkdir()
    for args, message in (
        (("--out", folder), "is a directory: give a file name in it"),
        (("--out", tmp_path / "x.png"), "written as an OpenEXR file: give a file name ending in .exr"),
        (("--out", tmp_path / "y.exr", "--preview", tmp_path / "p.jpg"), "written as a PNG file"),
        (("--out", tmp_path / "z.exr", "--report", folder), "is a directory"),
    ):
        r = run(tyndall_exe, "render", scene, *args, "--quiet")
        assert r.returncode == 1 and message in r.stderr, r.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a", "b", "d", "folder", "s.json"]
    assert list(folder.iterdir()) == []


def test_report_path_may_not_replace_another_output_or_the_scene(
    tyndall_exe: Path, small_scene: Callable[..., SceneDict], tmp_path: Path
) -> None:
    """`--report` was never checked: `--report o.exr` left JSON text in the image and
    `--report scene.json` replaced the scene (exit 0 both times)."""
    scene = tmp_path / "s.json"
    text = json.dumps(small_scene())
    scene.write_text(text)
    out = tmp_path / "o.exr"
    for args, message in (
        (("--report", out), "the report is written as JSON"),
        (("--report", scene), "is the input"),
        (("--report", tmp_path / "sub" / ".." / "s.json"), "is the input"),
        (("--preview", tmp_path / "p.png", "--report", tmp_path / "r.png"), "the report is written as JSON"),
    ):
        r = run(tyndall_exe, "render", scene, "--out", out, *args, "--quiet")
        assert r.returncode == 1 and message in r.stderr, r.stderr
    assert scene.read_text() == text
    assert not out.exists()


def test_long_output_names_get_their_report(
    tyndall_exe: Path, small_scene: Callable[..., SceneDict], tmp_path: Path
) -> None:
    """A 240-byte image name is legal, and so is its report's; the report's temporary
    file was named after it (`.<name>.<pid>.tmp`, over 255 bytes) and the write failed."""
    scene = tmp_path / "s.json"
    scene.write_text(json.dumps(small_scene()))
    out = tmp_path / ("x" * 236 + ".exr")
    r = run(tyndall_exe, "render", scene, "--out", out, "--quiet")
    assert r.returncode == 0, r.stderr
    assert json.loads(out.with_suffix(".report.json").read_text())["resolution"] == [40, 30]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["s.json", out.name, out.stem + ".report.json"])


def test_bench_sizes_out_of_range_are_usage_errors(tyndall_exe: Path) -> None:
    """`tyndall bench --width 0` (or 70000, or --threads 5000) panicked in the bench scene."""
    for args in (("--width", "0"), ("--width", "70000"), ("--height", "0"), ("--threads", "5000")):
        r = run(tyndall_exe, "bench", *args, "--repeat", "1")
        assert r.returncode == 2, (args, r.stderr)
        assert "panicked" not in r.stderr and "Traceback" not in r.stderr
        assert args[0] in r.stderr


def test_render_prints_the_reports_warnings(
    tyndall_exe: Path, small_scene: Callable[..., SceneDict], tmp_path: Path
) -> None:
    """Warnings went only into the report JSON; the summary now counts them and the
    command prints each on stderr (here: a light at the camera's position)."""
    spot = {"type": "spot", "name": "at_eye", "position": [0.0, 0.0, 1.5], "power_w": 100.0,
            "orientation": {"look_at": {"target": [0.0, 10.0, 1.5]}}}
    scene = tmp_path / "s.json"
    scene.write_text(json.dumps(small_scene(lights=[spot])))
    r = run(tyndall_exe, "render", scene, "--out", tmp_path / "o.exr")
    assert r.returncode == 0, r.stderr
    report = json.loads((tmp_path / "o.report.json").read_text())
    assert report["warnings"], report
    for w in report["warnings"]:
        assert f"tyndall: warning: {w}" in r.stderr
    assert f"; {len(report['warnings'])} warnings" in r.stdout
    assert "pixels not converged" in r.stdout


def test_ctrl_c_stops_a_render(tyndall_exe: Path, small_scene: Callable[..., SceneDict], tmp_path: Path) -> None:
    """Ctrl-C (SIGINT) left `tyndall render` running to its end (rc 0, files written):
    the interpreter is released during the render, so Python's handler never ran."""
    import signal
    import time

    spot = {"type": "spot", "name": "s", "position": [0.5, 8.0, 4.0], "power_w": 500.0, "spot_size_deg": 40}
    big = small_scene(lights=[spot])
    big["camera"]["resolution"] = [640, 480]
    big["output"] = {"threads": 1, "tolerance": 1e-6}
    scene = tmp_path / "s.json"
    scene.write_text(json.dumps(big))
    proc = subprocess.Popen(
        [str(tyndall_exe), "render", str(scene), "--out", str(tmp_path / "o.exr"), "--quiet"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE,
    )
    time.sleep(1.0)
    assert proc.poll() is None, "the render must still be running when Ctrl-C comes"
    start = time.monotonic()
    proc.send_signal(signal.SIGINT)
    rc = proc.wait(timeout=30)
    assert time.monotonic() - start < 2.0
    assert rc != 0
    assert not (tmp_path / "o.exr").exists() and not (tmp_path / "o.report.json").exists()
