"""A real Slurm, not a mock: start a single-node Slurm on this machine and send a small matrix through
hydra/launcher=cluster (make slurm-check; needs root and Debian's slurm-wlm and munge).

What it does, in order, and fails with one line at the first thing that goes wrong:
1. starts munged, slurmctld and slurmd for this host alone (cluster/slurm.conf.in: this host's CPUs and memory from
   `slurmd -C`, a fresh munge key, state and logs in a temporary folder; no accounting, no cgroups) and waits until
   sinfo shows the node idle;
2. generates frictioncubes_0 and frictioncubes_1 with the tests' small splits (6/4/4 tosses) into
   outputs/slurm_check/data, and sends {mujoco_default, gnn} x those two variants at budget=smoke, scored on test,
   through hydra/launcher=cluster as one Slurm array;
3. kills the GNN job on frictioncubes_0 mid-training with `scontrol requeue` (its smoke budget is lengthened to
   GNN_MAX_STEPS steps so that it runs long enough, with a validation and checkpoint every GNN_VAL_INTERVAL steps),
   lets Slurm start it again, and checks that the second attempt resumed from the checkpoint instead of starting
   over: Slurm counts one restart, the run's train.log says it resumed from that last.ckpt, Lightning that it
   restored all states from it, and csv/metrics.csv holds the first attempt's rows below the checkpoint's step
   unchanged and the second attempt's from there to max_steps, no step twice (a run started over logs them again);
4. runs the report on the sweep and checks that it counts every job done;
5. stops slurmd, slurmctld and munged (also on failure or Ctrl-C) and prints the wall time.

Sweep output goes to outputs/slurm_check/<time>/ (git-ignored); Slurm's state and logs are deleted after a pass and
kept (their folder is printed) after a failure.
"""

from __future__ import annotations

import argparse
import csv
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
TEMPLATE = Path(__file__).with_name("slurm.conf.in")
OUTPUT_ROOT = REPO_ROOT / "outputs" / "slurm_check"
DAEMONS = ("munged", "slurmctld", "slurmd")
CLIENTS = ("sinfo", "squeue", "sbatch", "scontrol", "scancel")
PARTITION = "check"
KILL_WAIT = 5  # seconds from SIGTERM to SIGKILL when Slurm requeues or cancels a job
MODELS = ("mujoco_default", "gnn")
VARIANTS = ("frictioncubes_0", "frictioncubes_1")
SPLITS = "{train:6,val:4,test:4}"  # the tests' small splits (tests/test_pipeline.py, smoke_train_sweep)
GNN_MAX_STEPS = 1500  # budget=smoke trains 20 steps, over before a job could be killed
GNN_VAL_INTERVAL = 100  # a validation every this many steps (Lightning 2.6 writes last.ckpt at one that improves)
KILL_AT_STEP = 300  # requeue once last.ckpt holds at least this many steps
KILLED = {"model": "gnn", "variant": "frictioncubes_0"}  # the job that is killed and must resume
MEM_GB = 2
TIMEOUT_MIN = 15


class CheckFailed(Exception):
    """What went wrong, in one line."""


class Terminated(BaseException):
    """SIGTERM: stop as after a failure (a BaseException, so that no `except Exception` on the way swallows it)."""


def _terminated(*_) -> None:
    raise Terminated


def say(message: str) -> None:
    print(f"slurm-check: {message}", flush=True)


def run(command: list[str], env: dict | None = None, timeout: float = 60, check: bool = True) -> str:
    """A command's stdout; CheckFailed with its exit status and last line of stderr when it fails."""
    try:
        result = subprocess.run(command, capture_output=True, text=True, env=env, timeout=timeout, cwd=REPO_ROOT)
    except subprocess.TimeoutExpired:
        raise CheckFailed(f"`{' '.join(command)}` did not finish within {timeout:g} s") from None
    if check and result.returncode != 0:
        last = (result.stderr.strip() or result.stdout.strip() or "no output").splitlines()[-1]
        raise CheckFailed(f"`{' '.join(command)}` exited {result.returncode}: {last}")
    return result.stdout


def wait_for(condition, timeout: float, what: str, interval: float = 0.5):
    """condition()'s first truthy value within timeout seconds, else CheckFailed naming what was awaited."""
    deadline = time.monotonic() + timeout
    while True:
        value = condition()
        if value:
            return value
        if time.monotonic() > deadline:
            raise CheckFailed(f"timed out after {timeout:g} s waiting for {what}")
        time.sleep(interval)


def node_hardware() -> tuple[str, dict[str, str]]:
    """This host's name and hardware as slurmd sees it (`slurmd -C`): CPUs, sockets, cores, threads, memory."""
    first = run(["slurmd", "-C"]).splitlines()[0]
    fields = dict(item.split("=", 1) for item in first.split())
    keys = ("CPUs", "Boards", "SocketsPerBoard", "CoresPerSocket", "ThreadsPerCore", "RealMemory")
    return fields["NodeName"], {key: fields[key] for key in keys if key in fields}


def free_ports(count: int) -> list[int]:
    sockets = [socket.socket() for _ in range(count)]
    try:
        for item in sockets:
            item.bind(("", 0))
        return [item.getsockname()[1] for item in sockets]
    finally:
        for item in sockets:
            item.close()


def alive(pid: int) -> bool:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


class Cluster:
    """munged, slurmctld and slurmd of this host, with their state in a temporary folder; stop() ends exactly the
    daemons start() started (by the pids they wrote) and any job still queued."""

    def __init__(self) -> None:
        self.state = Path(tempfile.mkdtemp(prefix="contactbench-slurm-"))
        self.state.chmod(0o755)  # munged wants its socket's folders searchable by everyone
        self.conf = self.state / "slurm.conf"
        self.env = {key: value for key, value in os.environ.items() if not key.startswith("SLURM_")}
        self.env["SLURM_CONF"] = str(self.conf)
        self.pids: dict[str, int] = {}
        self.pid_files: dict[str, Path] = {}
        self.host = ""
        self.hardware: dict[str, str] = {}

    def start(self) -> None:
        self.host, self.hardware = node_hardware()
        munge = self.state / "munge"
        munge.mkdir(mode=0o755)
        for name in ("slurmctld", "slurmd"):
            (self.state / name).mkdir()
        key = munge / "munge.key"
        key.write_bytes(os.urandom(1024))
        key.chmod(0o400)
        controller_port, node_port = free_ports(2)
        values = {
            "HOST": self.host,
            "NODE_HARDWARE": " ".join(f"{name}={value}" for name, value in self.hardware.items()),
            "CTLD_PORT": controller_port,
            "SLURMD_PORT": node_port,
            "STATE": self.state,
            "PARTITION": PARTITION,
            "KILL_WAIT": KILL_WAIT,
        }
        text = TEMPLATE.read_text()
        for name, value in values.items():
            text = text.replace(f"@{name}@", str(value))
        unfilled = re.findall(r"@[A-Z_]+@", text)
        if unfilled:
            raise CheckFailed(f"{TEMPLATE}: placeholder {unfilled[0]} is not one the check fills in")
        self.conf.write_text(text)
        self._daemon(
            "munged",
            [
                "munged",
                f"--socket={munge / 'munge.socket'}",
                f"--key-file={key}",
                f"--pid-file={munge / 'munged.pid'}",
                f"--log-file={munge / 'munged.log'}",
                f"--seed-file={munge / 'munged.seed'}",
            ],
            munge / "munged.pid",
        )
        self._daemon("slurmctld", ["slurmctld", "-f", str(self.conf)], self.state / "slurmctld.pid")
        self._daemon("slurmd", ["slurmd", "-f", str(self.conf)], self.state / "slurmd.pid")
        wait_for(self._idle, 60, f"sinfo to show node {self.host} idle (logs: {self.state})")

    def _daemon(self, name: str, command: list[str], pid_file: Path) -> None:
        self.pid_files[name] = pid_file
        result = subprocess.run(command, capture_output=True, text=True, env=self.env, timeout=60)
        if result.returncode != 0:
            last = (result.stderr.strip() or result.stdout.strip() or "no output").splitlines()[-1]
            raise CheckFailed(f"{name} did not start (`{' '.join(command)}` exited {result.returncode}: {last})")

        def started() -> int | None:
            try:
                pid = int(pid_file.read_text().split()[0])
            except (OSError, ValueError, IndexError):
                return None
            return pid if alive(pid) else None

        self.pids[name] = wait_for(started, 30, f"{name} to write {pid_file} (logs: {self.state})")

    def _idle(self) -> bool:
        states = run(["sinfo", "-h", "-N", "-n", self.host, "-o", "%T"], env=self.env, check=False).split()
        return states == ["idle"]

    def slurm(self, *arguments: str, check: bool = True) -> str:
        return run(list(arguments), env=self.env, check=check)

    def stop(self) -> list[str]:
        """Cancel whatever is still queued, then end slurmd, slurmctld and munged; the names of the daemons ended."""
        if "slurmctld" in self.pids and alive(self.pids["slurmctld"]):
            jobs = self.slurm("squeue", "-h", "-o", "%i", check=False).split()
            if jobs:
                self.slurm("scancel", *jobs, check=False)
                try:
                    wait_for(lambda: not self.slurm("squeue", "-h", check=False).strip(), KILL_WAIT + 30, "jobs")
                except CheckFailed:
                    pass
        stopped = []
        for name in reversed(DAEMONS):
            pid = self.pids.get(name)
            if pid is None:  # it may have started without our seeing its pid file in time
                try:
                    pid = int(self.pid_files[name].read_text().split()[0])
                except (KeyError, OSError, ValueError, IndexError):
                    continue
            if not alive(pid) or not Path(f"/proc/{pid}/comm").read_text().strip().startswith(name[:15]):
                continue
            os.kill(pid, signal.SIGTERM)
            try:
                wait_for(lambda pid=pid: not alive(pid), 15, f"{name} to exit", interval=0.2)
            except CheckFailed:
                os.kill(pid, signal.SIGKILL)
            stopped.append(name)
        return stopped


def checkpoint_step(path: Path) -> int | None:
    """global_step of a Lightning checkpoint; None while it is missing or half written."""
    import torch

    try:
        return int(torch.load(path, weights_only=True, map_location="cpu")["global_step"])
    except Exception:  # noqa: BLE001 - not there yet, or being written: ask again
        return None


def job_state(cluster: Cluster, job: str) -> str:
    return cluster.slurm("squeue", "-h", "-j", job, "-o", "%T", check=False).strip()


def tail(path: Path, lines: int = 15) -> str:
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-lines:])
    except OSError:
        return f"({path} is missing)"


def generate_data(data: Path, log_dir: Path) -> None:
    command = [
        sys.executable,
        "generate.py",
        "-m",
        "variant=" + ",".join(VARIANTS),
        f"generation.split_sizes={SPLITS}",
        f"paths.data_dir={data}",
        f"paths.log_dir={log_dir}",
    ]
    run(command, timeout=600)


def sweep_command(data: Path, log_dir: Path, sweep: Path, extra: list[str]) -> list[str]:
    return [
        sys.executable,
        "train.py",
        "-m",
        "hydra/launcher=cluster",
        f"hydra.launcher.partition={PARTITION}",
        "hydra.launcher.gpus_per_node=null",
        "hydra.launcher.cpus_per_task=1",
        f"hydra.launcher.mem_gb={MEM_GB}",
        f"hydra.launcher.timeout_min={TIMEOUT_MIN}",
        "budget=smoke",
        "model=" + ",".join(MODELS),
        "variant=" + ",".join(VARIANTS),
        "test=true",
        # the GNN's smoke budget, lengthened so one job can be killed mid-training (a key mujoco_default ignores)
        f"++model.budgets.smoke.max_steps={GNN_MAX_STEPS}",
        f"++model.budgets.smoke.val_check_interval={GNN_VAL_INTERVAL}",
        f"paths.data_dir={data}",
        f"paths.log_dir={log_dir}",
        f"hydra.sweep.dir={sweep}",
        *extra,
    ]


def submitted_jobs(controller_log: Path) -> dict[int, str]:
    """The sweep's jobs as Hydra's submitit launcher logs them, '#<index> : <overrides>'; index = array task id."""
    text = controller_log.read_text(errors="replace") if controller_log.exists() else ""
    return {int(index): overrides.strip() for index, overrides in re.findall(r"#(\d+) : (.*)", text)}


def job_folder(sweep: Path, values: dict[str, str]) -> Path | None:
    for folder in sweep.iterdir():
        if folder.is_dir() and all(f",{key}={value}," in f",{folder.name}," for key, value in values.items()):
            return folder
    return None


def check(cluster: Cluster, extra: list[str]) -> None:
    cluster.start()
    version = run(["slurmd", "-V"]).strip()
    say(
        f"{version} up on {cluster.host} ({cluster.hardware.get('CPUs')} CPUs, "
        f"{cluster.hardware.get('RealMemory')} MB), partition {PARTITION}; state and logs in {cluster.state}"
    )

    run_dir = OUTPUT_ROOT / time.strftime("%Y-%m-%d_%H-%M-%S")
    data, sweep, controller_log = OUTPUT_ROOT / "data", run_dir / "sweep", run_dir / "controller.log"
    run_dir.mkdir(parents=True)
    moment = time.monotonic()
    generate_data(data, run_dir)
    say(f"data: {', '.join(VARIANTS)} ({SPLITS} tosses) in {data} ({time.monotonic() - moment:.0f} s)")

    command = sweep_command(data, run_dir, sweep, extra)
    say("sweep: " + " ".join(command[1:]))
    env = {**cluster.env, "WANDB_MODE": "disabled"}
    with controller_log.open("w") as output:
        controller = subprocess.Popen(command, cwd=REPO_ROOT, env=env, stdout=output, stderr=subprocess.STDOUT)
    try:
        killed = drive(cluster, controller, controller_log, sweep)
        code = controller.wait(timeout=900)
    except subprocess.TimeoutExpired:
        raise CheckFailed(f"the sweep did not finish within 15 minutes (its log: {controller_log})") from None
    finally:
        if controller.poll() is None:
            controller.terminate()
            try:
                controller.wait(timeout=10)
            except subprocess.TimeoutExpired:
                controller.kill()
    if code != 0:
        raise CheckFailed(f"train.py -m exited {code}; its log ({controller_log}) ends:\n{tail(controller_log)}")
    jobs = submitted_jobs(controller_log)
    say(f"sweep finished: train.py -m exited 0 after its {len(jobs)} Slurm jobs")

    job, folder, checkpoint = killed.job, killed.folder, killed.checkpoint

    def finished_show() -> str | None:
        # submitit reads the job's result file as soon as it is written; Slurm marks the job COMPLETED only after
        # the process has exited and the epilog ran, a moment later on a loaded node
        show = cluster.slurm("scontrol", "show", "job", job)
        state = re.search(r"\bJobState=(\S+)", show)
        return None if state and state.group(1) in ("RUNNING", "COMPLETING") else show

    show = wait_for(finished_show, timeout=120, what=f"job {job} to leave RUNNING", interval=1)
    restarts = re.search(r"\bRestarts=(\d+)", show)
    state = re.search(r"\bJobState=(\S+)", show)
    if not restarts or int(restarts.group(1)) != 1 or not state or state.group(1) != "COMPLETED":
        raise CheckFailed(
            f"scontrol show job {job}: JobState={state and state.group(1)} Restarts={restarts and restarts.group(1)} "
            "(expected COMPLETED after 1 restart)"
        )
    resumed_lines = [
        line for line in (folder / "train.log").read_text().splitlines() if f"resuming from {checkpoint}" in line
    ]
    if len(resumed_lines) != 1:
        raise CheckFailed(
            f"{folder / 'train.log'}: {len(resumed_lines)} 'resuming from {checkpoint}' lines (expected 1)"
        )
    restored = [
        line
        # Lightning logs through Python's logging, which the job's Hydra logging config sends to stdout
        for path in sorted((sweep / ".submitit" / job).glob("*_log.*"))
        for line in path.read_text(errors="replace").splitlines()
        if "Restored all states from the checkpoint" in line and str(checkpoint) in line
    ]
    if not restored:
        raise CheckFailed(f"{sweep / '.submitit' / job}: no Lightning 'Restored all states from {checkpoint}' line")
    rows = train_rows(folder, killed.prefix)
    steps = [step for step, _ in rows]
    kept = [(step, values) for step, values in rows if step < killed.step]
    same = len(kept) == len(killed.rows_before) and all(
        step == step_before and all(values.get(name) == value for name, value in before.items())
        for (step, values), (step_before, before) in zip(kept, killed.rows_before)
    )
    new = [step for step in steps if step >= killed.step]
    metrics_csv = folder / "csv" / "metrics.csv"
    if len(set(steps)) != len(steps):
        twice = sorted({step for step in steps if steps.count(step) > 1})
        raise CheckFailed(f"{metrics_csv}: steps {twice[:5]}... logged twice: the second attempt trained them again")
    if not same:
        raise CheckFailed(f"{metrics_csv}: the rows before step {killed.step} differ from the first attempt's")
    if not new or max(new) < GNN_MAX_STEPS - 10:
        raise CheckFailed(
            f"{metrics_csv}: the second attempt logged steps {new[:1]}..{new[-1:]} (expected up to max_steps)"
        )
    say(f"evidence that {job} resumed from step {killed.step} (<run> = {folder}):")
    say(f"  scontrol show job {job}: JobState=COMPLETED Restarts=1")
    say(f"  <run>/train.log: {resumed_lines[0].replace(str(folder), '<run>')}")
    say(f"  {job}'s stderr (Lightning): {restored[0].replace(str(folder), '<run>')}")
    say(
        f"  <run>/csv/metrics.csv, {killed.prefix or ''}train/loss: steps {steps[0]}..{kept[-1][0]} ({len(kept)} rows) "
        f"as the first attempt logged them, {new[0]}..{new[-1]} ({len(new)} rows) from the second; none twice"
    )

    moment = time.monotonic()
    report = run([sys.executable, "-m", "contactbench.evaluation.report", str(sweep)], timeout=600)
    counts = re.search(
        r"(\d+) jobs asked for: (\d+) done, (\d+) skipped, (\d+) failed, (\d+) unfinished, (\d+) missing", report
    )
    if not counts:
        raise CheckFailed(f"{sweep / 'results.md'}: no 'N jobs asked for: ...' line (not the report of a sweep?)")
    asked, done = int(counts.group(1)), int(counts.group(2))
    if asked != len(MODELS) * len(VARIANTS) or done != asked:
        raise CheckFailed(f"{sweep / 'results.md'}: {counts.group(0)} (expected every one of {len(jobs)} done)")
    say(f"report: {counts.group(0)} ({sweep / 'results.md'}, {time.monotonic() - moment:.0f} s)")
    say(f"jobs submitted {len(jobs)}, jobs done {done}; requeued {job} resumed from step {killed.step}")


def drive(cluster: Cluster, controller: subprocess.Popen, controller_log: Path, sweep: Path) -> Killed:
    """Wait for the sweep's jobs, kill the chosen GNN job mid-training with scontrol requeue, let Slurm run it again,
    and see its second attempt start."""
    total = len(MODELS) * len(VARIANTS)

    def submitted() -> dict[int, str] | None:
        if controller.poll() is not None:
            raise CheckFailed(
                f"train.py -m exited {controller.returncode} early; its log ends:\n{tail(controller_log)}"
            )
        jobs = submitted_jobs(controller_log)
        return jobs if len(jobs) == total and list(sweep.glob(".submitit/*_*")) else None

    jobs = wait_for(submitted, 120, f"train.py -m to submit {total} jobs")
    index = next(
        index
        for index, overrides in jobs.items()
        if all(f"{key}={value}" in overrides.split() for key, value in KILLED.items())
    )
    array = wait_for(lambda: next(iter(sweep.glob(f".submitit/*_{index}")), None), 60, "the job's submitit folder")
    job = array.name
    array_id = job.split("_")[0]
    say(f"submitted {len(jobs)} jobs as Slurm array {array_id}:")
    for number, overrides in sorted(jobs.items()):
        shown = " ".join(item for item in overrides.split() if item.split("=")[0] in ("model", "variant"))
        say(f"  {array_id}_{number}: {shown}")
    folder = wait_for(lambda: job_folder(sweep, KILLED), 300, f"the run folder of job {job}")

    def ready_to_kill() -> tuple[Path, int] | None:
        state = job_state(cluster, job)
        if state != "RUNNING" and (folder / "test" / "metrics.json").exists():
            raise CheckFailed(
                f"job {job} finished before it could be killed (raise GNN_MAX_STEPS in {Path(__file__).name})"
            )
        if state != "RUNNING":
            return None
        training = [(path, step) for path, step in last_checkpoints(folder).items() if step and step < GNN_MAX_STEPS]
        return training[0] if training and training[0][1] >= KILL_AT_STEP else None

    checkpoint, seen = wait_for(ready_to_kill, 600, f"job {job} to checkpoint step {KILL_AT_STEP}", interval=0.2)
    cluster.slurm("scontrol", "requeue", job)
    name = checkpoint.relative_to(folder)
    say(f"killed job {job} ({' '.join(f'{k}={v}' for k, v in KILLED.items())}) mid-training: scontrol requeue {job}")
    say(f"  ({name} held global_step {seen} of {GNN_MAX_STEPS} when it was requeued)")
    wait_for(lambda: job_state(cluster, job) == "PENDING", 60, f"job {job} to be pending again")
    time.sleep(KILL_WAIT + 1)  # the first attempt's processes get SIGKILL after KillWait at the latest
    left = last_checkpoints(folder)
    killed_at = left.get(checkpoint)
    if killed_at is None or not 0 < killed_at < GNN_MAX_STEPS:
        raise CheckFailed(f"{checkpoint}: global_step {killed_at} after the kill (expected 0 < step < {GNN_MAX_STEPS})")
    prefix = "/".join(checkpoint.parent.relative_to(folder / "checkpoints").parts)
    prefix = f"{prefix}/" if prefix else ""
    rows_before = [(step, values) for step, values in train_rows(folder, prefix) if step < killed_at]
    if not rows_before:
        raise CheckFailed(f"{folder / 'csv' / 'metrics.csv'}: no {prefix}train/loss rows before step {killed_at}")
    reason = cluster.slurm("squeue", "-h", "-j", job, "-o", "%r").strip()
    # A requeued batch job waits until its old credential expires (about 2 minutes: Reason=BeginTime); this check
    # lets it start now. A real cluster simply starts it later.
    cluster.slurm("scontrol", "update", f"JobId={job}", "StartTime=now")
    state = ", ".join(f"{path.relative_to(folder)} at step {step}" for path, step in left.items())
    say(f"  job {job} is PENDING again (reason {reason}), its checkpoints: {state}; released it now")
    wait_for(lambda: job_state(cluster, job) != "PENDING", 120, f"job {job} to start again")
    say(f"  job {job} started its second attempt")
    return Killed(job, folder, checkpoint, killed_at, prefix, rows_before)


@dataclass
class Killed:
    """The job killed mid-training: its id, run folder, the checkpoint it was training into and that checkpoint's
    step when it was killed, the metric prefix of that fit and the train rows it had logged below that step."""

    job: str
    folder: Path
    checkpoint: Path
    step: int
    prefix: str
    rows_before: list


def train_rows(folder: Path, prefix: str) -> list[tuple[int, dict]]:
    """(step, that row's values of the fit's columns) for every train/loss row in csv/metrics.csv, in file order."""
    path = folder / "csv" / "metrics.csv"
    if not path.is_file():
        return []
    with path.open(newline="") as file:
        return [
            (int(float(row["step"])), {name: value for name, value in row.items() if name.startswith(prefix)})
            for row in csv.DictReader(file)
            if row.get(f"{prefix}train/loss")
        ]


def last_checkpoints(folder: Path) -> dict[Path, int | None]:
    """Every last.ckpt of a run folder (one per setting a model chooses on val: checkpoints/<setting>/last.ckpt),
    most recently written first, with its global_step."""
    paths = sorted((folder / "checkpoints").rglob("last.ckpt"), key=lambda path: -path.stat().st_mtime_ns)
    return {path: checkpoint_step(path) for path in paths}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "overrides",
        nargs="*",
        help="more Hydra overrides for the sweep (resume=false must make the check fail: the job starts over)",
    )
    arguments = parser.parse_args()
    started = time.monotonic()
    missing = [name for name in (*DAEMONS, *CLIENTS) if shutil.which(name) is None]
    if missing:
        print(
            f"slurm-check: error: {', '.join(missing)} not found; install Slurm and munge first: "
            "apt-get install slurm-wlm munge",
            file=sys.stderr,
        )
        return 2
    if os.geteuid() != 0:
        print("slurm-check: error: must run as root (slurmd starts jobs as their user)", file=sys.stderr)
        return 2
    signal.signal(signal.SIGTERM, _terminated)  # a killed check still stops its daemons
    cluster = Cluster()
    passed = False
    try:
        check(cluster, arguments.overrides)
        passed = True
    except CheckFailed as failure:
        say(f"FAILED: {failure}")
    except (KeyboardInterrupt, Terminated) as stop:
        say(f"FAILED: {'interrupted' if isinstance(stop, KeyboardInterrupt) else 'terminated (SIGTERM)'}")
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_IGN)  # a second SIGTERM must not cut the clean-up short
        stopped = cluster.stop()
        say(f"stopped {', '.join(stopped) or 'nothing (no daemon was running)'}")
        if passed:
            shutil.rmtree(cluster.state, ignore_errors=True)
        else:
            say(f"Slurm's and munge's logs kept in {cluster.state}")
    say(f"{'passed' if passed else 'failed'} in {time.monotonic() - started:.0f} s")
    return 0 if passed else 1


if __name__ == "__main__":
    sys.exit(main())
