"""CLI start-up, as a cell controller scripting ``scancell`` pays it: whole processes, medians.

- ``scancell --help`` (target <= 0.30 s) and ``scancell ctl status`` against a running daemon on
  the mock cell (target <= 0.5 s), each beside ``python -c pass`` measured in the same run;
- ``scancell decode`` as a whole process on a 1280 x 1024, 3 x 3 scene rendered by the simulated
  cell, against ``benchmarks/reference_decode.py`` (plain numpy + OpenCV, the same work) in the
  same run (target: ratio <= 0.6), and its decode in process as it prints it (target <= 0.30 s).

Run: .venv/bin/python benchmarks/bench_cli_startup.py  (or `make bench`)
"""

from __future__ import annotations

import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from scancell.bus.ports import free_port

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
SCANCELL = [str(Path(sys.executable).with_name("scancell"))]
RUNS = 7


def timed(cmd: list[str], env: dict[str, str] | None = None, runs: int = RUNS) -> float:
    """Median wall time (s) of ``runs`` runs of ``cmd`` (which must exit 0)."""
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        subprocess.run(cmd, check=True, env=env, stdout=subprocess.DEVNULL,
                       stderr=subprocess.DEVNULL)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def render_scene(out: Path) -> None:
    """One station of the car rear at 1280 x 1024 (camera scale 2448/1280), true calibration."""
    import cv2
    from scancell.model.patterns import FringeSequence
    from scancell.sim.cell import SimCell, SimCellConfig

    cell = SimCell(SimCellConfig(camera_scale=2448 / 1280))
    target = cell.cfg.T_world_from_part[:3, 3] + [-200.0, 0, 0]
    cell.move_joints(cell.ik_for_mcs(cell.mcs_pose_looking_at(target, 600.0)))
    cell.load_sequence(FringeSequence())
    for role in ("left", "right"):
        (out / role).mkdir(parents=True)
        for k, img in enumerate(cell.render_sequence(role)):
            cv2.imwrite(str(out / role / f"{k:02d}.png"), img)
    cell.rig.write_opencv_yaml(out / "stereo.yaml")


def _decode_seconds(args: list[str]) -> float:
    """The decode time ``scancell decode`` prints (frames in memory -> cloud, s)."""
    import re

    out = subprocess.run([*SCANCELL, "decode", *args], check=True, capture_output=True,
                         text=True).stdout
    return float(re.search(r"decode (\d+\.\d+) s", out).group(1))


def main() -> dict[str, float]:
    python = timed([sys.executable, "-c", "pass"])
    help_s = timed([*SCANCELL, "--help"])
    print(f"python -c pass          {python:.3f} s (reference)")
    print(f"scancell --help         {help_s:.3f} s  (ratio {help_s / python:.1f}; target <= 0.30 s)")

    port = free_port()
    env = dict(os.environ, SCANCELL_CONNECT=f"tcp/127.0.0.1:{port}", SCANCELL_CELL="mock")
    daemon = subprocess.Popen([*SCANCELL, "daemon", "--config",
                               str(ROOT / "deploy" / "cells" / "mock.toml"),
                               "--listen", f"tcp/127.0.0.1:{port}"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 30
        while subprocess.run([*SCANCELL, "ctl", "status"], env=env,
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL).returncode:
            if time.monotonic() > deadline:
                raise RuntimeError("the mock daemon did not answer within 30 s")
            time.sleep(0.3)
        status = timed([*SCANCELL, "ctl", "status"], env)
    finally:
        daemon.terminate()
        daemon.wait(10)
    print(f"scancell ctl status     {status:.3f} s  (ratio {status / python:.1f}; target <= 0.5 s)")

    with tempfile.TemporaryDirectory() as tmp:
        scene = Path(tmp)
        render_scene(scene)
        args = ["--calib", str(scene / "stereo.yaml"), "--images", str(scene),
                "--out", str(scene / "out.ply")]
        ours = timed([*SCANCELL, "decode", *args], runs=5)
        ref = timed([sys.executable, str(HERE / "reference_decode.py"), *args], runs=5)
        in_process = statistics.median(_decode_seconds(args) for _ in range(5))
    print(f"scancell decode         {in_process:.3f} s  in process (frames read -> cloud, "
          f"compensation and uncertainty on; target <= 0.30 s)")
    print(f"scancell decode         {ours:.3f} s  (1280 x 1024, 3 x 3, whole process)")
    print(f"reference_decode.py     {ref:.3f} s  (plain numpy, whole process)")
    print(f"ratio                   {ours / ref:.2f}  (target <= 0.6)")
    return {"python_s": python, "help_s": help_s, "ctl_status_s": status, "decode_s": ours,
            "reference_decode_s": ref, "decode_ratio": ours / ref}


if __name__ == "__main__":
    main()
