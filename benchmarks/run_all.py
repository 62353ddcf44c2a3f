"""`make bench`: run every benchmark script in this folder, one after the other."""

from __future__ import annotations

import pathlib
import runpy

HERE = pathlib.Path(__file__).resolve().parent


def main() -> int:
    failed = []
    for path in sorted(HERE.glob("bench_*.py")):
        print(f"\n### {path.stem}", flush=True)
        try:
            runpy.run_path(str(path), run_name="__main__")
        except SystemExit as exc:  # a script's own exit ends that script, not the run
            if exc.code not in (None, 0):
                failed.append(path.stem)
                print(f"{path.stem} exited with {exc.code}", flush=True)
    if failed:
        print(f"\nfailed: {', '.join(failed)}")
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
