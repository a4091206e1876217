"""Real PX4 SITL instances (the built-in SIH fixed-wing airplane) for tests and benchmarks.

The PX4 folder (``bin/px4`` and ``etc/``) comes from the environment variable ``PX4_SITL``
(``.ci/run`` sets it when ``../shared/sitl/px4/bin/px4`` exists); tests skip with the reason
without it (the ``px4_sitl`` fixture of tests/sitl/conftest.py). PX4 is a test peer, never part
of the project.

Use::

    with Px4Swarm(px4_root, homes, speedup=5) as swarm:
        swarm.connect_args()       # ["--connect", "udpout:127.0.0.1:18590", ...]  (GCS links)
        swarm.payload_args()       # ["--connect", "udpout:127.0.0.1:14600", ...]  (onboard links)
        swarm.kill(1)              # SIGKILL one instance (its process group)

How an instance is started (../shared/sitl/px4/README.md):

* A runtime folder per swarm holds ``bin/px4`` (a symlink to the real binary) and one
  ``px4-<command>`` symlink to it per command of ``px4-alias.sh``: PX4's startup scripts run
  those commands through PATH (a shared folder whose symlinks were copied as plain files makes
  every ``param set`` fail with "Permission denied").
* Each instance gets a work folder of its own (``-w``; a fresh one: no ``parameters.bson`` from
  an earlier run) and a hooks folder first in PATH whose ``px4-rc.params`` (sourced by PX4's
  rcS after its defaults) turns logging off (SDLOG_MODE -1) and sets the system id: vehicle i
  is system id i + 1 whatever its instance number N, so instance numbers are taken free at
  start (a lock file per number, and the UDP ports 18570+N, 14580+N, 14280+N, 13030+N and
  19450+N free), never assumed.
* The hooks folder's ``px4-rc.mavlink`` (sourced by rcS in place of PX4's) starts the GCS link
  (18570+N) and the onboard link (14580+N) in PX4's Normal mode at its default rates, as over a
  telemetry radio (GLOBAL_POSITION_INT 5 Hz, ATTITUDE 15 Hz of the vehicle's clock), and no
  SIH display or gimbal link: PX4's SITL script adds 50 Hz streams (GLOBAL_POSITION_INT,
  ATTITUDE, ...) and a 200 Hz actuator stream, ~1750 messages a second per plane at 5x; with
  three planes the daemon's step computation took 12.7 s instead of 0.4 and it refused 5x.
* PX4 starts every MAVLink instance with ``-f`` (forwarding on): what the payload simulator
  says on the onboard link (14580+N; the camera, component 100) reaches the daemon on the GCS
  link (18570+N), and the daemon's capture requests reach the camera.
* Each PX4 link answers the first peer that talks to it (send a HEARTBEAT first).
"""

from __future__ import annotations

import os
import re
import socket
import subprocess
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

from sitl_harness import AutopilotProcess, AutopilotSwarm, Home, InstanceLock, claim_instance

ENV_VAR = "PX4_SITL"
MAX_INSTANCE = 200
FIRST_INSTANCE = 10  # leave 0..9 to people starting PX4 by hand with the README's numbers
PORT_BASES = (18570, 14580, 14280, 13030, 19450)
#: the MAVLink links an instance opens (sourced by PX4's rcS with ``px4_instance`` set)
RC_MAVLINK = """#!/bin/sh
# harness hook: found via PATH before etc/init.d-posix (tests/sitl/px4_harness.py)
gcs=$((18570+px4_instance))
mavlink start -x -u $gcs -r 400000 -f
mavlink start -x -u $((14580+px4_instance)) -r 400000 -f -o $((14540+px4_instance))
"""


def px4_root_from_env() -> Path | None:
    """The PX4 SITL folder named by ``PX4_SITL`` (holding bin/px4 and etc/), or None."""
    value = os.environ.get(ENV_VAR, "")
    if not value:
        return None
    root = Path(value)
    binary = root / "bin" / "px4"
    ok = binary.is_file() and os.access(binary, os.X_OK) and (root / "etc").is_dir()
    return root if ok else None


def skip_reason() -> str:
    """Why PX4 SITL tests cannot run here (for pytest.skip)."""
    value = os.environ.get(ENV_VAR, "")
    if not value:
        return (
            f"{ENV_VAR} is not set: point it at a PX4 SITL folder with bin/px4 and etc/ "
            "(.ci/run sets it when ../shared/sitl/px4/bin/px4 exists)"
        )
    return f"{ENV_VAR}={value} has no executable bin/px4 and etc/ folder"


def _udp_port_free(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def _claim_instance(start_at: int) -> InstanceLock:
    """The lowest free PX4 instance number >= ``start_at``: PX4's UDP ports of it free."""
    return claim_instance(
        "px4", start_at, lambda n: all(_udp_port_free(base + n) for base in PORT_BASES)
    )


def runtime_bin(root: Path, folder: Path) -> Path:
    """``folder``/bin: px4 (a symlink to ``root``/bin/px4) and a px4-<command> symlink to it for
    every command PX4's ``px4-alias.sh`` names."""
    bin_dir = folder / "bin"
    bin_dir.mkdir(parents=True, exist_ok=True)
    px4 = bin_dir / "px4"
    if not px4.exists():
        px4.symlink_to((root / "bin" / "px4").resolve())
    alias_file = bin_dir / "px4-alias.sh"
    if not alias_file.exists():
        alias_file.symlink_to((root / "bin" / "px4-alias.sh").resolve())
    aliases = alias_file.read_text()
    for command in re.findall(r"^alias [a-z0-9_]+='px4-([a-z0-9_]+) ", aliases, re.MULTILINE):
        link = bin_dir / f"px4-{command}"
        if not link.exists():
            link.symlink_to("px4")
    return bin_dir


@dataclass
class Px4Vehicle(AutopilotProcess):
    """One running PX4 SITL instance: vehicle ``index`` (system id index + 1)."""

    index: int
    instance: int
    workdir: Path
    home: Home
    _lock: InstanceLock = field(repr=False)
    command: list[str] = field(default_factory=list, repr=False)
    env: dict[str, str] = field(default_factory=dict, repr=False)
    process: subprocess.Popen | None = None  # None until launched
    niceness: int = 0

    @property
    def master(self) -> str:
        """The GCS link (the daemon's)."""
        return f"udpout:127.0.0.1:{18570 + self.instance}"

    @property
    def payload(self) -> str:
        """The onboard link (the payload simulator's)."""
        return f"udpout:127.0.0.1:{14580 + self.instance}"

    @property
    def log_path(self) -> Path:
        return self.workdir / "px4.log"

    def launch(self) -> None:
        """Start the instance in its own process group (its output to ``log_path``)."""
        with open(self.log_path, "w") as log:
            self.process = subprocess.Popen(
                self.command, cwd=self.workdir, env=self.env, stdout=log,
                stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, start_new_session=True,
                preexec_fn=(lambda: os.nice(self.niceness)) if self.niceness else None,
            )  # fmt: skip


class Px4Swarm(AutopilotSwarm):
    """N PX4 SIH airplanes, vehicle i with system id ``first_system_id + i`` at ``homes[i]``.

    ``params`` (name -> value) are set by the hook after PX4's defaults; ``niceness`` lowers
    the instances' CPU priority (``os.nice``). ``workdir`` (default: a
    fresh temporary folder, removed at stop) holds the runtime bin and one folder per vehicle.
    """

    def __init__(
        self,
        root: Path | str,
        homes: list[Home],
        *,
        speedup: float = 1.0,
        params: dict[str, float] | None = None,
        workdir: Path | None = None,
        first_system_id: int = 1,
        niceness: int = 0,
    ) -> None:
        self.root = Path(root)
        self.niceness = niceness
        self.homes = list(homes)
        self.speedup = speedup
        self.params = dict(params or {})
        self.first_system_id = first_system_id
        self._tmp = None if workdir is not None else tempfile.TemporaryDirectory(prefix="px4-")
        self.workdir = Path(self._tmp.name) if self._tmp is not None else Path(workdir)
        self.vehicles: list[Px4Vehicle] = []

    def start(self) -> None:
        """Start every instance (each in its own process group); returns at once: PX4 answers
        its first HEARTBEAT about 1.3 s after start and can arm about 5.4 s after."""
        self.claim()
        self.launch()

    def launch(self) -> None:
        """Start the instances :meth:`claim` prepared."""
        for vehicle in self.vehicles:
            if vehicle.process is None:
                vehicle.launch()

    def claim(self) -> None:
        """Take an instance number (and so its ports: ``connect_args``, ``payload_args``) and a
        work folder for every vehicle, without starting PX4 yet (:meth:`launch`): a client
        such as the daemon can be started first, e.g. so that it measures its own pace before
        the PX4 instances take the machine's CPU."""
        bin_dir = runtime_bin(self.root, self.workdir)
        for index, home in enumerate(self.homes):
            lock = _claim_instance(FIRST_INSTANCE if not self.vehicles else
                                   self.vehicles[-1].instance + 1)  # fmt: skip
            folder = self.workdir / f"v{index}"
            hooks = folder / "hooks"
            hooks.mkdir(parents=True, exist_ok=True)
            sysid = self.first_system_id + index
            settings = {"SDLOG_MODE": -1, "MAV_SYS_ID": sysid, **self.params}
            (hooks / "px4-rc.params").write_text(
                "".join(f"param set {k} {v:g}\n" for k, v in settings.items())
            )
            (hooks / "px4-rc.mavlink").write_text(RC_MAVLINK)
            env = dict(os.environ)
            env.update(
                PATH=f"{hooks}:{env.get('PATH', '/usr/bin:/bin')}",
                PX4_SIM_MODEL="sihsim_airplane",
                PX4_SIMULATOR="sihsim",
                PX4_HOME_LAT=f"{home.lat_deg:.7f}",
                PX4_HOME_LON=f"{home.lon_deg:.7f}",
                PX4_HOME_ALT=f"{home.alt_m:.1f}",
            )
            if self.speedup != 1:
                env["PX4_SIM_SPEED_FACTOR"] = f"{self.speedup:g}"
            command = [str(bin_dir / "px4"), "-d", "-i", str(lock.number), "-w",
                       str(folder / "work"), str(self.root.resolve() / "etc")]  # fmt: skip
            self.vehicles.append(
                Px4Vehicle(
                    sysid - 1, lock.number, folder, home, lock, command, env,
                    niceness=self.niceness,
                )  # fmt: skip
            )
