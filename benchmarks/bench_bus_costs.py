"""What one message costs on the bus, for the 10-cell estimate in RESULTS.md (issue 22).

Three processes on loopback, as cells on several machines would run: a publisher (zenoh client),
a hub (the listening peer a daemon or router is, forwarding) and a subscriber (client), with
shared memory off everywhere (between machines there is none). Each run publishes flat out for a
few seconds; every process reports its CPU seconds.

- small: 250-byte JSON samples (a tracker point, a joint state, a status), blocking congestion
  control, one key: messages per second and CPU microseconds per message in each process;
- frames: 5.0 MB images (2448 x 2048 mono8) the same way: MB/s and CPU seconds per GB.

Reference, same run: the frames published straight to a subscriber that is itself the
listening peer (no forwarding hop); the ratio hub / direct is the forwarding hop's cost.

Run: .venv/bin/python benchmarks/bench_bus_costs.py [--seconds 5]  (or `make bench`)
"""

from __future__ import annotations

import argparse
import json
import resource
import signal
import subprocess
import sys
import threading
import time

from scancell.bus.ports import free_port

CELL = "costs"
FRAME = 2448 * 2048


def _cpu() -> float:
    ru = resource.getrusage(resource.RUSAGE_SELF)
    return ru.ru_utime + ru.ru_stime


# ---------------------------------------------------------------- roles (subprocesses)


def role_pub(ep: str, size: int, seconds: float) -> None:
    from scancell.bus import Bus, BusConfig
    from scancell.protocols.encoding import Encoded

    bus = Bus.open(BusConfig(mode="client", connect=(ep,), shared_memory_mb=0), CELL, wait_s=20)
    payload = Encoded(b"x" * size, "application/json", "scancell.TrackerPoint")  # never parsed
    key = bus.keys.dev("bench", "data")
    time.sleep(1.0)
    cpu0, t0, n = _cpu(), time.monotonic(), 0
    while time.monotonic() - t0 < seconds:
        bus.publish(key, payload)
        n += 1
    print(json.dumps({"sent": n, "cpu_s": _cpu() - cpu0}), flush=True)
    bus.close()


def role_node(ep: str, listen: bool, count: bool) -> None:
    """The hub (listen, no subscription) or a subscriber (listen when it is the hub itself)."""
    from scancell.bus import Bus, BusConfig

    cfg = (BusConfig(listen=(ep,), shared_memory_mb=0) if listen
           else BusConfig(mode="client", connect=(ep,), shared_memory_mb=0))
    bus = Bus.open(cfg, CELL, wait_s=20)
    stats = {"n": 0, "bytes": 0, "first": None, "last": None}
    lock = threading.Lock()

    def on_sample(s) -> None:
        now = time.monotonic()
        with lock:
            stats["n"] += 1
            stats["bytes"] += len(s.payload)
            stats["first"] = stats["first"] or now
            stats["last"] = now

    if count:
        bus.subscribe(bus.keys.dev("bench", "data"), on_sample)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    cpu0 = _cpu()
    print("ready", flush=True)
    stop.wait()
    with lock:
        out = dict(stats, cpu_s=_cpu() - cpu0)
    print(json.dumps(out), flush=True)
    bus.close()


# ---------------------------------------------------------------- orchestration


def _spawn(*args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, __file__, *args], stdout=subprocess.PIPE, text=True)


def run(size: int, seconds: float, hop: bool) -> dict[str, float]:
    ep = f"tcp/127.0.0.1:{free_port()}"
    nodes = []
    if hop:
        nodes.append(_spawn("--role", "node", "--ep", ep, "--listen"))
        assert nodes[0].stdout.readline().strip() == "ready"
        nodes.append(_spawn("--role", "node", "--ep", ep, "--count"))
    else:
        nodes.append(_spawn("--role", "node", "--ep", ep, "--listen", "--count"))
    assert nodes[-1].stdout.readline().strip() == "ready"
    time.sleep(1.0)
    pub = _spawn("--role", "pub", "--ep", ep, "--size", str(size), "--seconds", str(seconds))
    sent = json.loads(pub.stdout.readline())
    pub.wait(60)
    time.sleep(1.0)
    results = []
    for node in reversed(nodes):
        node.send_signal(signal.SIGTERM)
        results.append(json.loads(node.stdout.readline()))
        node.wait(30)
    sub = results[0]
    span = sub["last"] - sub["first"] if sub["n"] > 1 else float("nan")
    out = {"sent": sent["sent"], "received": sub["n"], "per_s": sub["n"] / span,
           "mb_s": sub["bytes"] / span / 1e6, "pub_cpu_s": sent["cpu_s"], "sub_cpu_s": sub["cpu_s"],
           "hub_cpu_s": results[1]["cpu_s"] if hop else 0.0}
    return out


def main(argv: list[str] | None = None) -> dict[str, float]:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=5.0)
    args = ap.parse_args(argv)
    small = run(250, args.seconds, hop=True)
    frames = run(FRAME, args.seconds, hop=True)
    direct = run(FRAME, args.seconds, hop=False)
    n = small["received"]
    print(f"small (250 B) via hub : {small['per_s']:8.0f} msg/s, {small['sent'] - n} lost; CPU per "
          f"message: publisher {1e6 * small['pub_cpu_s'] / n:.1f} us, hub "
          f"{1e6 * small['hub_cpu_s'] / n:.1f} us, subscriber {1e6 * small['sub_cpu_s'] / n:.1f} us")
    out = {"small_per_s": small["per_s"], "small_hub_us": 1e6 * small["hub_cpu_s"] / n,
           "small_sub_us": 1e6 * small["sub_cpu_s"] / n,
           "small_pub_us": 1e6 * small["pub_cpu_s"] / n}
    for name, r in (("frames via hub", frames), ("frames direct (reference)", direct)):
        gb = r["received"] * FRAME / 1e9
        print(f"{name:26s}: {r['mb_s']:7.0f} MB/s, {r['sent'] - r['received']} lost; CPU per GB: "
              f"publisher {r['pub_cpu_s'] / gb:.2f} s, hub {r['hub_cpu_s'] / gb:.2f} s, "
              f"subscriber {r['sub_cpu_s'] / gb:.2f} s")
        key = "hub" if r is frames else "direct"
        out.update({f"{key}_mb_s": r["mb_s"], f"{key}_hub_s_per_gb": r["hub_cpu_s"] / gb,
                    f"{key}_sub_s_per_gb": r["sub_cpu_s"] / gb,
                    f"{key}_pub_s_per_gb": r["pub_cpu_s"] / gb})
    print(f"ratio frames via hub / direct: {frames['mb_s'] / direct['mb_s']:.2f}")
    return out


if __name__ == "__main__":
    if "--role" in sys.argv:
        p = argparse.ArgumentParser()
        p.add_argument("--role")
        p.add_argument("--ep")
        p.add_argument("--size", type=int)
        p.add_argument("--seconds", type=float)
        p.add_argument("--listen", action="store_true")
        p.add_argument("--count", action="store_true")
        a = p.parse_args()
        if a.role == "pub":
            role_pub(a.ep, a.size, a.seconds)
        else:
            role_node(a.ep, a.listen, a.count)
    else:
        main()
