"""Real ArduPlane SITL instances for tests and benchmarks.

The binary's path comes from the environment variable ``ARDUPLANE_SITL`` (``.ci/run`` sets it
when ``../shared/sitl/arduplane`` exists next to the project); tests skip with a clear reason
without it (the ``sitl_binary`` fixture of tests/sitl/conftest.py). The binary is a test peer,
never part of the project.

Use::

    from sitl_harness import SitlSwarm, homes_for_scenario

    homes = homes_for_scenario(load_scenario("arduplane-3uav"))
    with SitlSwarm(binary, homes, speedup=10, params={"FENCE_ENABLE": 1}) as swarm:
        swarm.connect_args()          # ["--connect", "tcp:127.0.0.1:5760", "--connect", ...]
        swarm.vehicles[0].master      # "tcp:127.0.0.1:5760"  (MAVLink, SERIAL0)
        swarm.vehicles[0].payload     # "tcp:127.0.0.1:5762"  (SERIAL1: the payload simulator's)
        swarm.kill(1)                 # SIGKILL one instance (its process group)
    # leaving the block stops every instance (SIGTERM to its process group, then SIGKILL)

What an instance does (measured with the V4.8.0-dev binary of ../shared/sitl):

* Instance number N (``-I N``) shifts every port by 10 N: MAVLink on TCP 5760+10N (SERIAL0),
  SERIAL1 on 5762+10N and SERIAL2 on 5763+10N, both MAVLink. Before a client connects to SERIAL0
  only that port listens and the autopilot does not run ("Waiting for connection"); SERIAL1/2
  open once it boots. ``start()`` returns when SERIAL0 listens (read from /proc/net/tcp, without
  connecting, so the first client is the daemon).
* Vehicle i (0-based) gets system id i + 1 (``--sysid`` and SYSID_THISMAV). Free instance
  numbers are taken at start: an exclusive lock file per number (so parallel test processes on
  one machine never share one) and TCP ports 5760..5763 + 10N free.
* After the client connects it reports MAV_STATE_STANDBY within ~0.1 s, but can arm only ~20 s
  of its own clock later (EKF using GPS); SYS_STATUS bit MAV_SYS_STATUS_PREARM_CHECK tells when.
  With FENCE_ENABLE 1 arming is refused ("Fences enabled, but none selected") until a fence is
  uploaded.
* Each instance runs in its own working directory (eeprom.bin, logs), ``-w`` wipes parameters;
  its console output goes to ``<workdir>/arduplane.log``.
"""

from __future__ import annotations

import contextlib
import fcntl
import math
import os
import signal
import socket
import subprocess
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

ENV_VAR = "ARDUPLANE_SITL"
BASE_PORT = 5760
MAX_INSTANCE = 200
STOP_GRACE_S = 3.0


def sitl_binary_from_env() -> Path | None:
    """The ArduPlane SITL binary named by ``ARDUPLANE_SITL``, or None when it is unset or not an
    executable file."""
    value = os.environ.get(ENV_VAR, "")
    if not value:
        return None
    path = Path(value)
    return path if path.is_file() and os.access(path, os.X_OK) else None


def skip_reason() -> str:
    """Why SITL tests cannot run here (for pytest.skip)."""
    value = os.environ.get(ENV_VAR, "")
    if not value:
        return (
            f"{ENV_VAR} is not set: point it at an ArduPlane SITL binary "
            "(.ci/run sets it when ../shared/sitl/arduplane exists)"
        )
    return f"{ENV_VAR}={value} is not an executable file"


def plane_parm_for(binary: Path) -> Path:
    """ArduPilot's plane.parm (the defaults of ``--model plane``), kept beside the binary."""
    return binary.with_name("plane.parm")


@dataclass(frozen=True)
class Home:
    """Where an instance starts: degrees, metres AMSL, yaw in compass degrees."""

    lat_deg: float
    lon_deg: float
    alt_m: float
    yaw_deg: float = 0.0

    def arg(self) -> str:
        return f"{self.lat_deg:.7f},{self.lon_deg:.7f},{self.alt_m:.1f},{self.yaw_deg:.0f}"


def homes_for_scenario(scenario, seed: int = 0) -> list[Home]:
    """One home per UAV of a scenario: its start cell centre (``starts_for_seed``), at the
    origin's altitude, yaw from the start heading (counter-clockwise from east -> compass)."""
    from planner.geodesy import local_km_to_geodetic

    homes = []
    for start in scenario.starts_for_seed(seed):
        lat, lon = local_km_to_geodetic(start.x_km, start.y_km, scenario.origin)
        yaw = (90.0 - start.heading_deg) % 360.0
        homes.append(Home(float(lat[0]), float(lon[0]), scenario.origin.alt_m, yaw))
    return homes


def homes_near(
    lat_deg: float, lon_deg: float, count: int, spacing_m: float = 300.0, alt_m: float = 584.0
) -> list[Home]:
    """``count`` homes in a row west to east, ``spacing_m`` apart, facing north."""
    dlon = spacing_m / (111_320.0 * math.cos(math.radians(lat_deg)))
    return [Home(lat_deg, lon_deg + k * dlon, alt_m, 0.0) for k in range(count)]


def _tcp_port_free(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(("0.0.0.0", port))
        except OSError:
            return False
    return True


def _listening(port: int) -> bool:
    """Whether some socket listens on TCP ``port`` (read from /proc/net/tcp, no connection)."""
    want = f":{port:04X}"
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        try:
            with open(table) as f:
                next(f)
                for line in f:
                    parts = line.split()
                    if parts[1].endswith(want) and parts[3] == "0A":
                        return True
        except OSError:
            continue
    return False


@dataclass
class InstanceLock:
    """An instance number held by this process (a lock file under the temporary folder)."""

    number: int
    handle: object

    def release(self) -> None:
        try:
            fcntl.flock(self.handle, fcntl.LOCK_UN)
        finally:
            self.handle.close()


def claim_instance(
    kind: str, start_at: int, ports_free: Callable[[int], bool], max_instance: int = MAX_INSTANCE
) -> InstanceLock:
    """The lowest free instance number >= ``start_at`` of an autopilot ``kind`` (its lock
    folder's name): its lock file held and ``ports_free(number)``."""
    lock_dir = Path(tempfile.gettempdir()) / f"{kind}-sitl-locks"
    lock_dir.mkdir(exist_ok=True)
    for number in range(start_at, max_instance):
        handle = open(lock_dir / f"I{number}.lock", "w")  # noqa: SIM115 (held until release)
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            handle.close()
            continue
        if ports_free(number):
            return InstanceLock(number, handle)
        fcntl.flock(handle, fcntl.LOCK_UN)
        handle.close()
    raise RuntimeError(f"no free {kind} SITL instance number below {max_instance}")


def _claim_instance(start_at: int = 0) -> InstanceLock:
    """An ArduPlane instance number whose four TCP ports are free."""
    return claim_instance(
        "arduplane",
        start_at,
        lambda number: all(_tcp_port_free(BASE_PORT + 10 * number + k) for k in range(4)),
    )


class AutopilotProcess:
    """What an autopilot instance of a test does with its process group: ``index`` (vehicle
    ``index``, system id index + 1), ``process`` (None until launched), ``log_path`` and
    ``_lock`` are its subclass's."""

    index: int
    process: subprocess.Popen | None
    _lock: InstanceLock

    @property
    def system_id(self) -> int:
        return self.index + 1

    @property
    def log_path(self) -> Path:
        raise NotImplementedError

    def alive(self) -> bool:
        return self.process is not None and self.process.poll() is None

    def log_tail(self, lines: int = 15) -> str:
        try:
            return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-lines:])
        except OSError:
            return ""

    def signal(self, sig: int) -> None:
        """Send ``sig`` to the instance's process group (nothing if it has ended)."""
        if self.alive():
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.process.pid, sig)

    def kill(self, sig: int | None = None) -> None:
        """Send ``sig`` (default SIGKILL) to its process group and wait for its end (SIGKILL
        after the grace)."""
        self.signal(signal.SIGKILL if sig is None else sig)
        if self.process is None:
            return
        try:
            self.process.wait(STOP_GRACE_S)
        except subprocess.TimeoutExpired:
            self.signal(signal.SIGKILL)
            self.process.wait(STOP_GRACE_S)

    def stop(self, grace_s: float = STOP_GRACE_S) -> None:
        """SIGTERM to its process group, SIGKILL after ``grace_s``; releases its instance."""
        try:
            if self.alive():
                self.signal(signal.SIGTERM)
                try:
                    self.process.wait(grace_s)
                except subprocess.TimeoutExpired:
                    self.signal(signal.SIGKILL)
                    self.process.wait(grace_s)
        finally:
            if self._lock.handle and not self._lock.handle.closed:
                self._lock.release()


@dataclass
class SitlVehicle(AutopilotProcess):
    """One running ArduPlane SITL instance: vehicle ``index`` (system id index + 1)."""

    index: int
    instance: int
    workdir: Path
    process: subprocess.Popen
    home: Home
    _lock: InstanceLock = field(repr=False)

    @property
    def port(self) -> int:
        """SERIAL0, the autopilot's MAVLink port (the daemon's)."""
        return BASE_PORT + 10 * self.instance

    @property
    def payload_port(self) -> int:
        """SERIAL1, a second MAVLink port (the payload simulator's)."""
        return self.port + 2

    @property
    def master(self) -> str:
        return f"tcp:127.0.0.1:{self.port}"

    @property
    def payload(self) -> str:
        return f"tcp:127.0.0.1:{self.payload_port}"

    @property
    def log_path(self) -> Path:
        return self.workdir / "arduplane.log"


class AutopilotSwarm:
    """What a swarm of autopilot instances of a test shares: ``vehicles`` (each with a
    ``master`` and a ``payload`` endpoint), the temporary work folder ``_tmp`` (None when the
    caller gave one), ``start`` (its subclass's); a context manager that stops every instance."""

    vehicles: list
    _tmp: tempfile.TemporaryDirectory | None

    def start(self) -> None:
        raise NotImplementedError

    def __enter__(self):
        try:
            self.start()
        except BaseException:
            self.stop()
            raise
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def connect_args(self) -> list[str]:
        """``--connect`` options for ``swarmplan daemon``: every vehicle's GCS link."""
        return [arg for v in self.vehicles for arg in ("--connect", v.master)]

    def payload_args(self) -> list[str]:
        """``--connect`` options for the payload simulator: every vehicle's second link."""
        return [arg for v in self.vehicles for arg in ("--connect", v.payload)]

    def kill(self, index: int, sig: int = signal.SIGKILL) -> None:
        """Send ``sig`` (default SIGKILL) to vehicle ``index``'s instance and wait for its end."""
        self.vehicles[index].kill(sig)

    def stop(self) -> None:
        """Stop every instance (process group: SIGTERM, then SIGKILL) and remove the temporary
        folder. Safe to call more than once."""
        for vehicle in self.vehicles:
            vehicle.signal(signal.SIGTERM)
        for vehicle in self.vehicles:
            vehicle.stop()
        if self._tmp is not None:
            self._tmp.cleanup()
            self._tmp = None


class SitlSwarm(AutopilotSwarm):
    """N ArduPlane SITL instances, vehicle i with system id i + 1 at ``homes[i]``.

    ``params`` (name -> value) go into an extra defaults file after ArduPilot's plane.parm
    (``--defaults plane.parm,extra.parm``), e.g. ``{"FENCE_ENABLE": 1}``, and on top of them
    ``vehicle_params(index)`` for each vehicle's own (e.g. its node's MAV_GCS_SYSID).
    ``workdir`` (default: a fresh temporary folder, removed at stop) holds one folder per
    vehicle.
    """

    def __init__(
        self,
        binary: Path | str,
        homes: list[Home],
        *,
        speedup: float = 10.0,
        params: dict[str, float] | None = None,
        workdir: Path | None = None,
        start_timeout_s: float = 15.0,
        vehicle_params: Callable[[int], dict[str, float]] | None = None,
    ) -> None:
        self.binary = Path(binary)
        self.homes = list(homes)
        self.speedup = speedup
        self.params = dict(params or {})
        self.vehicle_params = vehicle_params or (lambda index: {})
        self.start_timeout_s = start_timeout_s
        self._tmp = None if workdir is not None else tempfile.TemporaryDirectory(prefix="sitl-")
        self.workdir = Path(workdir) if workdir is not None else Path(self._tmp.name)
        self.vehicles: list[SitlVehicle] = []

    def start(self) -> None:
        """Start every instance and wait (bounded) until each one's SERIAL0 listens."""
        parm = plane_parm_for(self.binary)
        if not parm.is_file():
            raise RuntimeError(f"{parm} is missing: plane.parm must sit beside the binary")
        next_number = 0
        for index, home in enumerate(self.homes):
            lock = _claim_instance(next_number)
            next_number = lock.number + 1
            folder = self.workdir / f"vehicle{index + 1}"
            folder.mkdir(parents=True, exist_ok=True)
            extra = folder / "extra.parm"
            values = {"SYSID_THISMAV": index + 1, **self.params, **self.vehicle_params(index)}
            extra.write_text("".join(f"{k} {v}\n" for k, v in values.items()))
            argv = [
                str(self.binary), "-w", "--model", "plane", "--speedup", f"{self.speedup:g}",
                "--sysid", str(index + 1), "-I", str(lock.number),
                "--defaults", f"{parm},{extra}", "--home", home.arg(),
            ]  # fmt: skip
            with open(folder / "arduplane.log", "wb") as log:
                proc = subprocess.Popen(
                    argv, cwd=folder, stdout=log, stderr=subprocess.STDOUT,
                    stdin=subprocess.DEVNULL, start_new_session=True,
                )  # fmt: skip
            self.vehicles.append(SitlVehicle(index, lock.number, folder, proc, home, lock))
        deadline = time.monotonic() + self.start_timeout_s
        for vehicle in self.vehicles:
            while not _listening(vehicle.port):
                if not vehicle.alive():
                    raise RuntimeError(
                        f"ArduPlane SITL vehicle {vehicle.system_id} exited at start "
                        f"(status {vehicle.process.returncode}):\n{vehicle.log_tail()}"
                    )
                if time.monotonic() > deadline:
                    raise RuntimeError(
                        f"ArduPlane SITL vehicle {vehicle.system_id} did not listen on TCP "
                        f"{vehicle.port} within {self.start_timeout_s:g} s:\n{vehicle.log_tail()}"
                    )
                time.sleep(0.05)
