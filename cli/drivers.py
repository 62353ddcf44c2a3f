"""``scancell drivers``: the device drivers scancell knows (built in and from entry points)."""

from __future__ import annotations

import argparse


def add_arguments(p: argparse.ArgumentParser) -> None:
    pass


def main(args: argparse.Namespace) -> int:
    from scancell.cli._common import table
    from scancell.devices.registry import available_drivers

    print(table(sorted(available_drivers().items()), ["DRIVER", "CLASS"]))
    return 0
