"""Recorder throughput: two cameras' worth of 2448 x 2048 mono8 images at 30 fps each
(2 x 150 MB/s = 300 MB/s) for 20 s through zenoh into ``scancell record``'s Recorder.

Reference, measured in the same run with the same processes, payloads and topology: a raw zenoh
subscriber that only counts the samples. Each run has two publisher processes (zenoh clients,
``scancell.bus.Bus.publish``, blocking congestion control) and one subscriber process (a listening
peer, as the daemon is). Figures: sustained MB/s, messages lost (sequence gaps at the subscriber)
and dropped (recorder queue), the subscriber's CPU, the recorder's lag behind the publishers, and
the ratio recorder / raw. A second pair of runs publishes as fast as it can (capacity), and a
third pair does the same with zenoh's shared-memory transport off in every process (issue 22):
the gain from shared memory on one host, in MB/s and in CPU seconds per GB on each side.

Run: .venv/bin/python benchmarks/bench_recorder_throughput.py [--seconds 20] (or `make bench`)
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from scancell.bus.ports import free_port

W, H = 2448, 2048
CELL = "bench"
DEFAULT_SHM_MB = 64  # scancell.bus.zenoh_bus.DEFAULT_SHM_MB, without importing zenoh here


# ---------------------------------------------------------------- roles (subprocesses)


def role_pub(ep: str, camera: str, fps: float, seconds: float, shm_mb: int) -> None:
    import numpy as np
    from scancell.bus import Bus, BusConfig
    from scancell.protocols import foxglove_schemas as fg

    bus = Bus.open(BusConfig(mode="client", connect=(ep,), shared_memory_mb=shm_mb), CELL,
                   wait_s=20)
    rng = np.random.default_rng(hash(camera) % 1000)
    img = rng.integers(0, 255, (H, W), dtype=np.uint8)  # incompressible, like sensor noise
    enc = fg.encode_proto(fg.raw_image(img, 0, camera))
    key = bus.keys.dev(camera, "image")
    time.sleep(1.0)
    t0 = time.monotonic()
    n = 0
    while time.monotonic() - t0 < seconds:
        bus.publish(key, enc)
        n += 1
        if fps > 0:
            delay = t0 + n / fps - time.monotonic()
            if delay > 0:
                time.sleep(delay)
    ru = resource.getrusage(resource.RUSAGE_SELF)
    print(json.dumps({"sent": n, "seconds": time.monotonic() - t0,
                      "cpu_s": ru.ru_utime + ru.ru_stime}), flush=True)
    bus.close()


def role_sub(ep: str, mode: str, out_dir: str, shm_mb: int) -> None:
    from scancell.bus import Bus, BusConfig

    bus = Bus.open(BusConfig(listen=(ep,), shared_memory_mb=shm_mb), CELL)
    stats = {"n": 0, "bytes": 0, "first": None, "last": None, "gaps": 0}
    last_seq: dict[str, int] = {}
    lock = threading.Lock()

    def count(s) -> None:
        now = time.monotonic()
        with lock:
            prev = last_seq.get(s.key)
            if prev is not None and s.attachment.seq != prev + 1:
                stats["gaps"] += s.attachment.seq - prev - 1
            last_seq[s.key] = s.attachment.seq
            stats["n"] += 1
            stats["bytes"] += len(s.payload)
            stats["first"] = stats["first"] or now
            stats["last"] = now

    recorder = None
    if mode == "recorder":
        from scancell.recorder.recorder import Recorder, RecorderSettings

        recorder = Recorder(bus, RecorderSettings(directory=out_dir, status_period_s=1.0),
                            {"bench": True})
        recorder.start()
        orig = recorder._on_sample

        def on_sample(s) -> None:  # count what reaches the recorder, then record it
            count(s)
            orig(s)

        recorder._on_sample = on_sample
        for sub in recorder._subs:
            sub.undeclare()
        recorder._subs = [bus.subscribe(bus.keys.dev("*", "image"), on_sample)]
    else:
        bus.subscribe(bus.keys.dev("*", "image"), count)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    print("ready", flush=True)
    stop.wait()
    while stats["last"] is not None and time.monotonic() - stats["last"] < 1.0:
        time.sleep(0.1)  # samples still in zenoh's buffers when the publishers returned
    t_stop = time.monotonic()
    with lock:
        result = dict(stats)
    if recorder is not None:
        recorder.stop()
        result.update(written=recorder.total_messages, written_bytes=recorder.total_bytes,
                      dropped=sum(recorder.dropped.values()), drain_s=time.monotonic() - t_stop,
                      files=[str(f) for f in recorder.files])
    ru = resource.getrusage(resource.RUSAGE_SELF)
    result["cpu_s"] = ru.ru_utime + ru.ru_stime
    bus.close()
    print(json.dumps(result), flush=True)


# ---------------------------------------------------------------- orchestration


def _spawn(*args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, __file__, *args], stdout=subprocess.PIPE, text=True)


def run(mode: str, fps: float, seconds: float, out_dir: str, shm_mb: int) -> dict:
    ep = f"tcp/127.0.0.1:{free_port()}"
    sub = _spawn("--role", "sub", "--ep", ep, "--mode", mode, "--out", out_dir,
                 "--shm", str(shm_mb))
    assert sub.stdout.readline().strip() == "ready"
    t0 = time.monotonic()
    pubs = [_spawn("--role", "pub", "--ep", ep, "--camera", cam, "--fps", str(fps),
                   "--seconds", str(seconds), "--shm", str(shm_mb))
            for cam in ("cam_left", "cam_right")]
    sent = [json.loads(p.stdout.readline()) for p in pubs]
    for p in pubs:
        p.wait(60)
    t_pub_end = time.monotonic()
    time.sleep(1.0)
    sub.send_signal(signal.SIGTERM)
    r = json.loads(sub.stdout.readline())
    sub.wait(120)
    r["sent"] = sum(s["sent"] for s in sent)
    r["pub_cpu_s"] = sum(s["cpu_s"] for s in sent)
    r["pub_seconds"] = max(s["seconds"] for s in sent)
    r["wall_s"] = t_pub_end - t0
    span = (r["last"] - r["first"]) if r["n"] > 1 else float("nan")
    r["mb_s"] = r["bytes"] / span / 1e6
    if "written_bytes" in r:  # on disk: until the writer had drained its queue
        r["write_mb_s"] = r["written_bytes"] / (span + r["drain_s"]) / 1e6
    r["cpu_share"] = r["cpu_s"] / (r["wall_s"] + 1.0)
    for f in r.get("files", []):
        r.setdefault("file_mb", 0.0)
        r["file_mb"] += Path(f).stat().st_size / 1e6
    return r


def plain_write_mb_s(folder: str, seconds: float = 5.0) -> float:
    """The disk's (page cache's) rate for plain 5 MB writes from Python: the write path's ceiling."""
    buf = os.urandom(W * H)
    path = Path(folder) / "plain.bin"
    t0, n = time.monotonic(), 0
    with open(path, "wb") as f:
        while time.monotonic() - t0 < seconds:
            f.write(buf)
            n += 1
    dt = time.monotonic() - t0
    path.unlink()
    return n * len(buf) / dt / 1e6


def _line(name: str, r: dict) -> str:
    extra = ""
    if "written" in r:
        extra = (f", written {r['written']} ({r['write_mb_s']:.0f} MB/s), dropped {r['dropped']}, drained "
                 f"{r['drain_s']:.2f} s after stop, file {r.get('file_mb', 0):.0f} MB")
    return (f"{name:28s} sent {r['sent']:5d}  received {r['n']:5d}  lost {r['gaps'] + r['sent'] - r['n']:3d}"
            f"  {r['mb_s']:7.1f} MB/s  subscriber CPU {100 * r['cpu_share']:5.1f} %{extra}")


def main(argv: list[str] | None = None) -> dict[str, float]:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--capacity-seconds", type=float, default=8.0)
    args = ap.parse_args(argv)
    tmp = tempfile.mkdtemp(prefix="scancell-bench-rec-")
    out: dict[str, float] = {}
    try:
        rows = {}
        for label, mode, fps, secs, shm in (
                ("raw zenoh, 2 x 30 fps", "raw", 30.0, args.seconds, DEFAULT_SHM_MB),
                ("recorder, 2 x 30 fps", "recorder", 30.0, args.seconds, DEFAULT_SHM_MB),
                ("raw zenoh, flat out", "raw", 0.0, args.capacity_seconds, DEFAULT_SHM_MB),
                ("recorder, flat out", "recorder", 0.0, args.capacity_seconds, DEFAULT_SHM_MB),
                ("raw zenoh, flat out, no SHM", "raw", 0.0, args.capacity_seconds, 0),
                ("recorder, flat out, no SHM", "recorder", 0.0, args.capacity_seconds, 0)):
            d = Path(tmp) / label.replace(" ", "_").replace(",", "")
            rows[label] = run(mode, fps, secs, str(d), shm)
            print(_line(label, rows[label]), flush=True)
            shutil.rmtree(d, ignore_errors=True)
        plain = plain_write_mb_s(tmp)
        print(f"{'plain file.write, 5 MB':28s} {plain:7.1f} MB/s (same disk, no zenoh, no MCAP)")
        raw, rec = rows["raw zenoh, 2 x 30 fps"], rows["recorder, 2 x 30 fps"]
        rawc, recc = rows["raw zenoh, flat out"], rows["recorder, flat out"]
        out = {"paced_raw_mb_s": raw["mb_s"], "paced_recorder_mb_s": rec["mb_s"],
               "paced_ratio": rec["mb_s"] / raw["mb_s"],
               "recorder_dropped": rec["dropped"] + recc["dropped"],
               "recorder_lost": rec["gaps"] + rec["sent"] - rec["n"],
               "capacity_raw_mb_s": rawc["mb_s"], "capacity_recorder_mb_s": recc["write_mb_s"],
               "capacity_ratio": recc["write_mb_s"] / rawc["mb_s"], "plain_write_mb_s": plain}
        for what in ("raw zenoh", "recorder"):
            on, off = rows[f"{what}, flat out"], rows[f"{what}, flat out, no SHM"]
            gb_on, gb_off = on["bytes"] / 1e9, off["bytes"] / 1e9
            print(f"shared memory, {what} flat out: {on['mb_s']:.0f} vs {off['mb_s']:.0f} MB/s "
                  f"without (x{on['mb_s'] / off['mb_s']:.2f}); CPU per GB: subscriber "
                  f"{on['cpu_s'] / gb_on:.2f} vs {off['cpu_s'] / gb_off:.2f} s, publishers "
                  f"{on['pub_cpu_s'] / gb_on:.2f} vs {off['pub_cpu_s'] / gb_off:.2f} s", flush=True)
            out[f"shm_{what.split()[0]}_ratio"] = on["mb_s"] / off["mb_s"]
        print(f"target 300 MB/s paced: recorder {rec['mb_s']:.0f} MB/s = {out['paced_ratio']:.2f} "
              f"of raw ({raw['mb_s']:.0f} MB/s), dropped {rec['dropped']}, lost "
              f"{out['recorder_lost']}; capacity {recc['write_mb_s']:.0f} vs raw {rawc['mb_s']:.0f} MB/s "
              f"= {out['capacity_ratio']:.2f}", flush=True)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out


if __name__ == "__main__":
    if "--role" in sys.argv:
        p = argparse.ArgumentParser()
        p.add_argument("--role")
        p.add_argument("--ep")
        p.add_argument("--camera")
        p.add_argument("--fps", type=float)
        p.add_argument("--seconds", type=float)
        p.add_argument("--mode")
        p.add_argument("--out")
        p.add_argument("--shm", type=int, default=0)
        a = p.parse_args()
        os.environ.setdefault("OMP_NUM_THREADS", "1")
        if a.role == "pub":
            role_pub(a.ep, a.camera, a.fps, a.seconds, a.shm)
        else:
            role_sub(a.ep, a.mode, a.out, a.shm)
    else:
        main()
