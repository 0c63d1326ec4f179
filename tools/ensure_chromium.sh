#!/usr/bin/env bash
# Headless Chromium from Debian's packages for the report's browser test (test/test_report.py
# skips without it). Installs only as root with apt-get; otherwise says why and exits 1.
set -euo pipefail
if command -v chromium >/dev/null; then exit 0; fi
if [ "$(id -u)" != 0 ] || ! command -v apt-get >/dev/null; then
  echo "chromium is not installed (apt-get install chromium as root)"; exit 1
fi
apt-get update -qq >/dev/null
DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null
