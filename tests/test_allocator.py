"""The long-running services keep freed memory (cli/_allocator.py)."""

from __future__ import annotations

import sys

import pytest
from scancell.cli import COMMANDS, LONG_RUNNING
from scancell.cli._allocator import keep_freed_memory


@pytest.mark.unit
def test_the_services_keep_freed_memory_where_glibc_lets_them():
    assert LONG_RUNNING <= set(COMMANDS)
    if sys.platform.startswith("linux"):
        assert keep_freed_memory() is True  # the CI machine: glibc
    else:
        assert keep_freed_memory() is False


@pytest.mark.unit
def test_the_heap_is_trimmed_once_each_time_the_process_falls_idle():
    from scancell.cli._allocator import IdleTrim

    trims: list[float] = []
    idle = IdleTrim(trim=lambda: trims.append(1), quiet_s=2.0, cpu_share=0.05)
    cpu = 0.0
    for t in range(0, 20):  # busy: a whole core for 10 s (0.5 s steps)
        cpu += 0.5
        idle.step(cpu, t * 0.5)
    assert not trims
    for t in range(20, 40):  # quiet for 10 s: one trim, 2 s into the quiet
        cpu += 0.001
        idle.step(cpu, t * 0.5)
    assert idle.trims == 1
    for t in range(40, 42):  # busy again, then quiet again: one more
        cpu += 0.5
        idle.step(cpu, t * 0.5)
    for t in range(42, 60):
        idle.step(cpu, t * 0.5)
    assert idle.trims == 2


@pytest.mark.process
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc_trim")
def test_memory_kept_after_a_free_goes_back_to_the_kernel_when_the_process_is_idle():
    import subprocess

    code = """
import time
import numpy as np
from scancell.cli._allocator import give_back_when_idle, keep_freed_memory

def rss_mb():
    return int(open("/proc/self/statm").read().split()[1]) * 4096 / 2**20

assert keep_freed_memory()
blocks = [np.ones(25 << 17) for _ in range(12)]  # 12 x 25 MB from the heap, below the mmap threshold
busy = rss_mb()
del blocks
kept = rss_mb()
give_back_when_idle(poll_s=0.1)
time.sleep(3.5)
print(busy, kept, rss_mb())
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    busy, kept, idle = map(float, out.stdout.split())
    assert kept > busy - 100, (busy, kept)  # freed, but kept: the heap keeps up to 1 GB
    assert idle < kept - 200, (busy, kept, idle)  # given back once idle


@pytest.mark.process
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc arenas")
def test_threads_share_one_arena_per_core():
    import subprocess

    # glibc's malloc_info lists each arena as a <heap nr=...>; without the limit each new thread
    # that allocates gets its own (up to 8 per core)
    code = """
import ctypes, ctypes.util, os, re, sys, tempfile, threading
import numpy as np
from scancell.cli._allocator import cores, keep_freed_memory

if sys.argv[1] == "limited":
    assert keep_freed_memory()
barrier = threading.Barrier(8)

def work():
    barrier.wait()
    for _ in range(20):
        np.ones(1 << 20).sum()  # 8 MB from the heap

threads = [threading.Thread(target=work) for _ in range(8)]
for t in threads:
    t.start()
for t in threads:
    t.join()
libc = ctypes.CDLL(ctypes.util.find_library("c"))
libc.fopen.restype = ctypes.c_void_p
libc.fopen.argtypes = [ctypes.c_char_p, ctypes.c_char_p]
libc.fclose.argtypes = [ctypes.c_void_p]
libc.malloc_info.argtypes = [ctypes.c_int, ctypes.c_void_p]
with tempfile.NamedTemporaryFile(delete=False) as f:
    path = f.name
fp = libc.fopen(path.encode(), b"w")
libc.malloc_info(0, fp)
libc.fclose(fp)
print(len(re.findall(r'<heap nr="', open(path).read())), cores())
os.unlink(path)
"""
    counts = {}
    for mode in ("limited", "default"):
        out = subprocess.run([sys.executable, "-c", code, mode], capture_output=True, text=True,
                             timeout=60)
        assert out.returncode == 0, out.stderr
        counts[mode], n_cores = map(int, out.stdout.split())
    assert counts["limited"] <= n_cores, counts
    assert counts["default"] > n_cores, counts  # the test can see the difference
