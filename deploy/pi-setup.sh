#!/usr/bin/env bash
# Raspberry Pi 5 (Raspberry Pi OS bookworm, aarch64): install the edge agent as a systemd service.
# Usage (on the Pi, from a checkout of the repository):
#   sudo deploy/pi-setup.sh /path/to/bundle
# where the bundle holds ca.pem, edge-<robot>.pem, edge-<robot>.key, edge-<robot>.password and edge.yaml
# (made on the CA machine, see docs/DEPLOY.md). Safe to run again (upgrades in place).
set -euo pipefail
BUNDLE=${1:?usage: pi-setup.sh BUNDLE_DIR}
REPO=$(cd "$(dirname "$0")/.." && pwd)
[ "$(id -u)" = 0 ] || { echo "run as root (sudo)"; exit 1; }
[ "$(uname -m)" = aarch64 ] || echo "warning: not aarch64 ($(uname -m)); continuing"

apt-get update
apt-get install -y --no-install-recommends python3-venv python3-dev chrony
# Clock sync matters: the edge drops commands whose timestamps are too old or in the future.
systemctl enable --now chrony

id iorthand >/dev/null 2>&1 || useradd --system --home /var/lib/iorthand --shell /usr/sbin/nologin iorthand
for g in dialout video gpio; do getent group $g >/dev/null && usermod -aG $g iorthand; done
install -d -o iorthand -g iorthand -m 0750 /var/lib/iorthand
install -d -o root -g iorthand -m 0750 /etc/iorthand /etc/iorthand/certs

python3 -m venv /opt/iorthand/venv
/opt/iorthand/venv/bin/pip install --upgrade pip
# aarch64 wheels exist for eclipse-zenoh, opencv-python-headless and ur-rtde: no compiler needed.
/opt/iorthand/venv/bin/pip install "$REPO" "$REPO/edge"

install -o root -g iorthand -m 0644 "$BUNDLE"/ca.pem "$BUNDLE"/edge-*.pem /etc/iorthand/certs/
install -o root -g iorthand -m 0640 "$BUNDLE"/edge-*.key "$BUNDLE"/edge-*.password /etc/iorthand/certs/
[ -f /etc/iorthand/edge.yaml ] || install -o root -g iorthand -m 0640 "$BUNDLE"/edge.yaml /etc/iorthand/edge.yaml

# As the service user: the check then also proves it can read every file it names.
runuser -u iorthand -- /opt/iorthand/venv/bin/iorthand check --config /etc/iorthand/edge.yaml
install -m 0644 "$REPO"/deploy/systemd/iorthand-edge.service /etc/systemd/system/
systemctl daemon-reload
systemctl enable --now iorthand-edge
systemctl --no-pager status iorthand-edge || true
echo "done: journalctl -u iorthand-edge -f to follow the agent"
