"""docs/DEPLOY.md followed on one machine, by its own commands.

The shell blocks of §1 (the CA), §2 (the cloud VM) and §4 (the operator's laptop) run as written, with four
substitutions: no ``sudo`` and no ``sudo -u iorthand`` (the test is root), no ``pip install`` (this checkout's
``iorthand`` is used, also for ``/opt/iorthand/venv/bin/iorthand``), the CA folder and the operator's name. Then the router, the twin and the recorder run with the installed configurations,
and an edge with ``deploy/configs/edge.yaml`` and its bundle installed as ``deploy/pi-setup.sh`` installs it; it
is armed through its local socket, and the operator moves the robot while the recorder records; the report is
written. Everything runs in new mount, network and PID namespaces: /etc is a copy (the documented ``useradd``
changes nothing outside), /var/lib/iorthand and /run/iorthand are empty, ``router.example.org`` is 127.0.0.1, port
7447 is free, and every process dies with the namespace. The services run as root here, because this venv's
interpreter is not readable by another user; that the ``iorthand`` user can read every file they need is checked
with that user's identity. Needs root, ``unshare`` and ``setpriv``; skips otherwise.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DEPLOY_DOC = ROOT / "docs" / "DEPLOY.md"
BIN = Path(sys.executable).parent


def shell_block(section: str) -> str:
    """The first ```bash block under the heading that starts with ``section`` (e.g. "## 2.")."""
    text = DEPLOY_DOC.read_text()
    start = text.index("\n" + section)
    block = re.search(r"```bash\n(.*?)```", text[start:], re.S)
    assert block is not None, f"no shell block under {section}"
    return block.group(1)


def as_run_here(block: str, ca: Path) -> str:
    lines = []
    for line in block.splitlines():
        if re.search(r"\bpip install\b", line):
            continue  # this checkout is installed already
        # As root, the service user's checks run as root (the READABLE step checks that user's access).
        line = line.replace("sudo -u iorthand ", "").replace("sudo ", "")
        line = line.replace("~/iorthand-ca", str(ca)).replace("operator-NAME", "operator-dr-martin")
        line = re.sub(r"(^|do |&& )(~/iorthand/bin/|/opt/iorthand/venv/bin/)?iorthand ", rf"\g<1>{BIN}/iorthand ", line)
        lines.append(line)
    return "\n".join(lines) + "\n"


def script(work: Path) -> str:
    ca, vm, laptop = work / "ca", work / "vm", work / "laptop"
    files_of_services = " ".join(
        f"/etc/iorthand/{f}" for f in ("router.json5", "users.txt", "twin.yaml", "recorder.yaml", "edge.yaml")) + " " + " ".join(
        f"/etc/iorthand/certs/{n}.{ext}" for n in ("router", "twin", "recorder", "edge-ur5e-lyon") for ext in ("pem", "key"))
    return f"""
set -euo pipefail
export PATH=/usr/sbin:/usr/bin:/sbin:/bin
step() {{ echo "=== $*"; }}
# This namespace's own /etc (a copy), state and runtime folders, loopback, and router name.
cp -a /etc {work}/etc && mount --bind {work}/etc /etc
echo "127.0.0.1 router.example.org" >> /etc/hosts
for d in /var/lib/iorthand /run/iorthand; do mkdir -p $d && mount -t tmpfs tmpfs $d; done
ip link set lo up

step CA
mkdir -p {ca}
{as_run_here(shell_block("## 1."), ca)}
step VM
mkdir -p {vm} && cd {vm} && ln -s {ROOT}/deploy deploy
cp {ca}/ca.pem {ca}/router.* {ca}/twin.* {ca}/recorder.* {ca}/replay.* {ca}/users.txt {ca}/deployment.yaml .
{as_run_here(shell_block("## 2."), ca)}
# What systemd does for the units: the state and runtime folders belong to the service user.
chown iorthand:iorthand /var/lib/iorthand /run/iorthand && chmod 0750 /var/lib/iorthand /run/iorthand

step PI
cd {ca}
# As deploy/pi-setup.sh installs the Pi's bundle.
install -o root -g iorthand -m 0644 ca.pem edge-*.pem /etc/iorthand/certs/
install -o root -g iorthand -m 0640 edge-*.key edge-*.password /etc/iorthand/certs/
install -o root -g iorthand -m 0640 {ROOT}/deploy/configs/edge.yaml /etc/iorthand/edge.yaml
{BIN}/iorthand check --config /etc/iorthand/edge.yaml

step READABLE
for f in {files_of_services} /etc/iorthand/certs/ca.pem /etc/iorthand/certs/edge-ur5e-lyon.password; do
  setpriv --reuid=iorthand --regid=iorthand --init-groups cat "$f" > /dev/null
done
echo "readable by iorthand: all"

step SERVICES
cd /var/lib/iorthand
{BIN}/iorthand router --config /etc/iorthand/router.json5 > {work}/router.log 2>&1 &
{BIN}/iorthand recorder --config /etc/iorthand/recorder.yaml > {work}/recorder.log 2>&1 &
{BIN}/iorthand twin --config /etc/iorthand/twin.yaml > {work}/twin.log 2>&1 &
{BIN}/iorthand edge --config /etc/iorthand/edge.yaml > {work}/edge.log 2>&1 &
for i in $(seq 100); do
  {BIN}/iorthand edge-status --config /etc/iorthand/edge.yaml > /dev/null 2>&1 && break
  sleep 0.2
done
{BIN}/iorthand arm --config /etc/iorthand/edge.yaml
for i in $(seq 30); do
  {BIN}/iorthand recorder status --config /etc/iorthand/recorder.yaml > /dev/null 2>&1 && break
done

step LAPTOP
mkdir -p {laptop}/home {laptop}/bundle && cd {laptop}/bundle && ln -s {ROOT}/deploy deploy
cp {ca}/ca.pem {ca}/operator-dr-martin.* .
export HOME={laptop}/home
{as_run_here(shell_block("## 4."), ca)}
step RECORD
{BIN}/iorthand recorder start --config /etc/iorthand/recorder.yaml --session e2e --operator dr-martin > /dev/null
{BIN}/iorthand operator --config ~/.config/iorthand/operator.yaml move --vx 0.005 --seconds 2 > {work}/move.json
{BIN}/iorthand recorder stop --config /etc/iorthand/recorder.yaml --session e2e > {work}/stop.json
{BIN}/iorthand report /var/lib/iorthand/recordings/e2e
test -s /var/lib/iorthand/recordings/e2e/report/report.md
step DONE
"""


@pytest.mark.slow
def test_the_deployment_guide_installs_a_working_system(tmp_path: Path) -> None:
    missing = [tool for tool in ("unshare", "setpriv", "ip") if shutil.which(tool) is None]
    if os.geteuid() != 0 or missing:
        pytest.skip(f"needs root and {', '.join(missing) or 'unshare, setpriv, ip'}")
    for folder in ("/var/lib/iorthand", "/run/iorthand"):  # mount points; empty, and left so
        os.makedirs(folder, exist_ok=True)
    driver = tmp_path / "deploy.sh"
    driver.write_text(script(tmp_path))
    # --kill-child: if this test is stopped (a timeout kills unshare), the namespace's first process dies, and with
    # it every process in the namespace.
    r = subprocess.run(["unshare", "--mount", "--net", "--pid", "--fork", "--kill-child", "--mount-proc",
                        "--propagation", "private", "bash", str(driver)], capture_output=True, text=True, timeout=200)
    logs = "".join(f"\n--- {p.name}\n{p.read_text()[-1500:]}" for p in sorted(tmp_path.glob("*.log")))
    assert r.returncode == 0 and "=== DONE" in r.stdout, f"{r.stdout[-4000:]}\n{r.stderr[-3000:]}{logs}"
    # iorthand check said OK of the router, twin, recorder, edge and operator configurations.
    assert len(re.findall(r"^  OK$", r.stdout, re.M)) == 5, r.stdout
    assert "readable by iorthand: all" in r.stdout
    move = json.loads((tmp_path / "move.json").read_text())
    assert move["refused"] == 0 and move["distance_mm"] > 5.0, move  # 5 mm/s for 2 s, under the 8 mm/s profile
    assert "robot ur5e-lyon: edge online" in (tmp_path / "twin.log").read_text()  # the twin is connected too
    stop = json.loads((tmp_path / "stop.json").read_text())
    assert stop["ok"] and stop["messages"] > 100 and stop["gaps"] == 0 and stop["dropped"] == 0, stop
