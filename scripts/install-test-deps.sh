#!/usr/bin/env bash
# System packages some tests use: Chromium (the twin's browser test), nftables (WAN blackouts), mosquitto
# (the MQTT baseline), shellcheck (the deployment scripts), stress-ng (the CPU hogs of benchmarks/bench_cpu_hogs.py),
# FFmpeg's shared libraries (torchcodec decodes a LeRobot dataset's videos with them), a C compiler (test_clock_steps.py
# builds a small LD_PRELOAD library that steps a process's wall clock: Debian's libfaketime breaks Python's sleep).
# Installed with apt when we are root; otherwise those tests skip and say why.
set -u
need=()
command -v chromium >/dev/null 2>&1 || need+=(chromium)
command -v nft >/dev/null 2>&1 || need+=(nftables)
command -v mosquitto >/dev/null 2>&1 || [ -x /usr/sbin/mosquitto ] || need+=(mosquitto)
command -v shellcheck >/dev/null 2>&1 || need+=(shellcheck)
command -v stress-ng >/dev/null 2>&1 || need+=(stress-ng)
command -v cc >/dev/null 2>&1 || need+=(gcc)
ldconfig -p | grep -q 'libavcodec.so.59' || need+=(libavcodec59 libavformat59 libavutil57 libswscale6 libswresample4 libavdevice59 libavfilter8)
[ ${#need[@]} -eq 0 ] && exit 0
if [ "$(id -u)" != 0 ] || ! command -v apt-get >/dev/null 2>&1; then
  echo "install-test-deps: not root or no apt-get: ${need[*]} not installed; the tests that need them will skip" >&2
  exit 0
fi
echo "install-test-deps: installing ${need[*]}" >&2
export DEBIAN_FRONTEND=noninteractive
apt-get update -qq >/dev/null 2>&1 || true
if ! apt-get install -y -qq --no-install-recommends "${need[@]}" >/dev/null 2>&1; then
  echo "install-test-deps: apt-get could not install ${need[*]}; the tests that need them will skip" >&2
fi
# mosquitto's package starts a system broker on 1883; the benchmark starts its own on a free port.
systemctl disable --now mosquitto >/dev/null 2>&1 || true
exit 0
