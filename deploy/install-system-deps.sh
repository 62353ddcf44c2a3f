#!/bin/sh
# Installs the system libraries scancell needs on Debian/Ubuntu: libusb-1.0-0 (loaded by open3d),
# openssl (the commissioning guide's certificates, checked by the tests) and
# chromium-headless-shell (the inspection report's test looks at it in a real browser), node and
# npm if missing (tests/js);
# with --bench also cloudcompare (the reference of benchmarks/bench_metrics.py).
# As root it uses apt-get; otherwise sudo when available; otherwise it prints the exact command.
set -eu
PKGS="libusb-1.0-0 openssl chromium-headless-shell"
[ "${1:-}" = "--bench" ] && PKGS="cloudcompare"
missing=""
for p in $PKGS; do
    dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing="$missing $p"
done
# node and npm: the tests drive the monitor with @foxglove/ws-protocol's own client (tests/js)
[ "${1:-}" = "--bench" ] || command -v npm >/dev/null 2>&1 || missing="$missing nodejs npm"
[ -z "$missing" ] && exit 0
cmd="apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq$missing"
if [ "$(id -u)" = 0 ]; then
    sh -c "$cmd"
elif command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then
    sudo sh -c "$cmd"
else
    echo "scancell needs system packages:$missing" >&2
    echo "install them as root with:  sudo sh -c '$cmd'" >&2
    exit 1
fi
