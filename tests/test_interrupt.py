"""SIGINT / SIGTERM: one line on stderr, exit 130 / 143, no traceback, no process left behind,
no partial output; plan-batch resumes after (issue 24, item 1).

The oracle is the operating system, not ctrplan: exit statuses from ``waitpid``, surviving
processes from ``/proc`` (every process of the command's session, plus the last-resort watchdog,
which runs in a session of its own), outputs from the file system. Fast tests here; the seeded
matrix of random moments over every command is ``@pytest.mark.statistical``.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

# one worker runs this file (`make test-stat` distributes by xdist group): its module fixtures
# are computed once
pytestmark = pytest.mark.xdist_group("interrupt")


ROOT = Path(__file__).resolve().parents[1]
# Fields that are not part of a plan's result: timings, and the work counters, which include
# the work of per-process caches (the retracted start is computed by the first job a process
# runs and reused by the next), so they depend on which process ran a job after which.
TIMING_KEYS = {"planning_time_s", "timings", "counts"}


# ---------------------------------------------------------------------------- helpers
def _procs() -> dict[int, tuple[int, list[str]]]:
    """pid -> (session id, argv) of every live (non-zombie) process."""
    out = {}
    for d in os.listdir("/proc"):
        if not d.isdigit():
            continue
        try:
            stat = Path(f"/proc/{d}/stat").read_text()
            argv = Path(f"/proc/{d}/cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        fields = stat[stat.rindex(")") + 2:].split()
        if fields[0] in ("Z", "X"):
            continue
        out[int(d)] = (int(fields[3]), [a.decode(errors="replace") for a in argv if a])
    return out


def survivors(pid: int, wait_s: float = 5.0) -> list[str]:
    """Processes left from the command ``pid`` started as a session leader: its session, and
    the watchdog (argv ``... -c SCRIPT PID GRACE FD``). Waits up to ``wait_s`` for them to go."""
    deadline = time.monotonic() + wait_s
    while True:
        left = [" ".join(argv)[:120] for p, (sid, argv) in _procs().items()
                if p != os.getpid() and (sid == pid or (len(argv) >= 4 and argv[-3] == str(pid)
                                                         and "-c" in argv))]
        if not left or time.monotonic() > deadline:
            return left
        time.sleep(0.1)


def cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "ctrplan.cli", "-q", *args]


class Run:
    """A command started in a session of its own, signalled after ``delay`` seconds."""

    def __init__(self, args: list[str], cwd: Path):
        self.started = time.monotonic()
        self.proc = subprocess.Popen(args, cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                     env=_env(), start_new_session=True)

    def signal_after(self, delay: float, sig: int, group: bool) -> tuple[bool, float | None]:
        """(whether the command was still running when signalled, seconds it took to end)."""
        try:
            self.proc.wait(timeout=delay)
            return False, None
        except subprocess.TimeoutExpired:
            pass
        if _exited(self.proc.pid):  # ended just after the wait timed out: not signalled
            self.proc.wait()
            return False, None
        t0 = time.monotonic()
        (os.killpg if group else os.kill)(self.proc.pid, sig)
        self.proc.wait(timeout=120)
        return True, time.monotonic() - t0

    def finish(self) -> tuple[int, str]:
        _, err = self.proc.communicate(timeout=600)
        return self.proc.returncode, err.decode(errors="replace")


#: Linux's per-task flag "the task is exiting" (``PF_EXITING``, the 9th field of /proc/PID/stat).
PF_EXITING = 0x4


def _exited(pid: int) -> bool:
    """True when the child is ending or has ended and is not reaped yet: a signal sent now is
    lost and its exit status is the command's own. That is a zombie, or a task already inside
    the kernel's exit (``PF_EXITING``): a process that has called ``_exit`` stays "R" for some
    10-20 ms while its memory is torn down, and a signal then changes nothing."""
    try:
        with open(f"/proc/{pid}/stat") as fh:
            fields = fh.read().rsplit(")", 1)[1].split()
        return fields[0] in ("Z", "X") or bool(int(fields[6]) & PF_EXITING)
    except (OSError, IndexError, ValueError):
        return False


def _env() -> dict:
    e = dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1")
    e.pop("PYTEST_CURRENT_TEST", None)
    return e


def assert_stopped(rc: int, err: str, sig: int) -> None:
    """Exit 128 + signal, one line naming the interruption, no traceback."""
    assert rc == 128 + sig, (rc, err)
    assert "Traceback" not in err and "Error" not in err.replace("InputError", ""), err
    word = "terminated" if sig == signal.SIGTERM else "interrupted"
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert sum(word in ln for ln in lines) == 1 and word in lines[-1], err


def job_files_complete(jobs_dir: Path) -> dict[str, dict]:
    """Every entry of a plan-batch jobs/ folder is a complete job JSON (no temporary left)."""
    out = {}
    for f in sorted(jobs_dir.iterdir()) if jobs_dir.exists() else []:
        assert not f.name.startswith("."), f"temporary left behind: {f}"
        data = json.loads(f.read_text())      # a torn file would not parse
        assert data["job_id"] == f.stem and "status" in data
        out[f.stem] = data
    return out


def without_timings(d: dict) -> dict:
    return {k: v for k, v in d.items() if k not in TIMING_KEYS}


# ---------------------------------------------------------------------------- fast tests
def _py(code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                          env=_env())


def test_deferred_region_records_and_raises_on_leaving():
    """Inside interrupt.deferred() (OMPL callbacks) a signal is recorded, not raised; leaving
    the region raises it; SIGTERM gives exit code 143."""
    r = _py(
        "import os, signal\n"
        "from ctrplan import interrupt\n"
        "with interrupt.guard():\n"
        "    try:\n"
        "        with interrupt.deferred():\n"
        "            os.kill(os.getpid(), signal.SIGTERM)\n"
        "            for _ in range(1000): pass\n"
        "            print('inside', interrupt.requested())\n"
        "        print('not raised')\n"
        "    except KeyboardInterrupt:\n"
        "        print('raised', interrupt.exit_code())\n")
    assert r.stdout.split("\n")[:2] == ["inside True", "raised 143"], (r.stdout, r.stderr)


def test_a_swallowed_interrupt_is_raised_again_at_the_next_import():
    """A library that swallows KeyboardInterrupt (trimesh imports its optional parts inside
    ``except BaseException``) does not stop the command from stopping."""
    r = _py(
        "import os, signal\n"
        "from ctrplan import interrupt\n"
        "with interrupt.guard():\n"
        "    try:\n"
        "        try:\n"
        "            os.kill(os.getpid(), signal.SIGINT)\n"
        "            for _ in range(1000): pass\n"
        "        except BaseException:\n"
        "            print('swallowed')\n"
        "        import json\n"
        "        print('not raised')\n"
        "    except KeyboardInterrupt:\n"
        "        print('raised', interrupt.exit_code())\n")
    assert r.stdout.split("\n")[:2] == ["swallowed", "raised 130"], (r.stdout, r.stderr)


_SPAWN_SCRIPT = """
import multiprocessing.process as mpp, os, signal, sys, time
import numpy as np
from ctrplan import interrupt

_start, _sent = mpp.BaseProcess.start, []

def start(self):
    _start(self)
    if not _sent:    # Ctrl-C, as a terminal sends it (to the whole group), as the first worker starts
        _sent.append(1)
        os.killpg(0, signal.SIGINT)

mpp.BaseProcess.start = start

def slow(x, planners=None):
    time.sleep(30)
    return x, 0.0

class SlowModel:
    name = "slow"
    def shape(self, q, points=20):
        time.sleep(30)

if __name__ == "__main__":
    with interrupt.guard():
        try:
            if sys.argv[1] == "pool":
                from ctrplan.planning.batch import _run_pool
                _run_pool([1, 2, 3], 2, print, fn=slow)
            elif sys.argv[1] == "runner":
                from ctrplan.design.runner import Runner
                with Runner(2, fn=slow) as r:
                    r.map([{"stage": "plan"}, {"stage": "plan"}, {"stage": "plan"}])
            else:
                from ctrplan.shape.dataset import simulate_shapes
                simulate_shapes(SlowModel(), np.zeros((3, 4)), workers=2, chunk=1, progress=False)
            print("finished", flush=True)
        except KeyboardInterrupt:
            print("interrupted", flush=True)
            sys.exit(130)
"""


@pytest.mark.parametrize("site", ["pool", "runner", "executor"])
def test_ctrl_c_while_workers_start_is_not_lost(tmp_path, site):
    """A Ctrl-C that comes while a pool's workers are being started (sent to the whole process
    group, as a terminal does, right after the first worker process exists) stops the command:
    the workers start with SIGINT blocked, so none prints a traceback, and the parent does not
    drop the signal (it used to ignore SIGINT while starting workers: plan-batch, reach, design
    and train then ran to the end and exited 0). Sites: the plan-batch/reach pool, the design
    search's runner, the training-data executor (fork)."""
    script = tmp_path / "spawn_interrupt.py"
    script.write_text(_SPAWN_SCRIPT)
    t0 = time.monotonic()
    proc = subprocess.Popen([sys.executable, str(script), site], cwd=tmp_path, env=_env(),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True)
    try:
        out, err = proc.communicate(timeout=120)
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
    out, err = out.decode(), err.decode()
    assert proc.returncode == 130 and out.split() == ["interrupted"], (proc.returncode, out, err)
    assert "Traceback" not in err and "Error" not in err, err
    assert time.monotonic() - t0 < 25, "the jobs ran (30 s each): the Ctrl-C was not acted on"
    assert survivors(proc.pid) == []


@pytest.fixture(scope="module")
def configs_200k(tmp_path_factory) -> Path:
    from ctrplan.robot import load_robot, write_configs

    robot = load_robot("seed1")
    path = tmp_path_factory.mktemp("cfg") / "q200k.csv"
    write_configs(path, robot, robot.sample(200_000, seed=24))
    return path


@pytest.mark.parametrize("sig,group", [(signal.SIGINT, True), (signal.SIGTERM, False)])
def test_shape_200k_rows_stops_within_a_second(tmp_path, configs_200k, sig, group):
    """`shape` on 200,000 rows: the mechanics kernel runs in chunks, so the signal is acted on
    at once (the old watchdog killed it with SIGKILL: exit 137, sometimes a segfault: 139)."""
    out = tmp_path / "out"
    out.mkdir()
    run = Run(cli("shape", "--robot", "seed1", "--configs", str(configs_200k), "--out",
                  str(out / "s.npz")), tmp_path)
    alive, latency = run.signal_after(3.0, sig, group)
    rc, err = run.finish()
    assert alive, "shape finished within 3 s: nothing was interrupted"
    assert_stopped(rc, err, sig)
    assert latency < 2.0, latency
    assert list(out.iterdir()) == []
    assert survivors(run.proc.pid) == []


def test_plan_batch_job_files_torn_or_temporary_are_redone(tmp_path):
    """A job file cut short (a crash in the middle of a write that was not atomic) is redone;
    temporaries of a killed run are removed; a second run on the same folder is refused."""
    import fcntl

    from ctrplan.errors import InputError
    from ctrplan.planning.batch import make_jobs, run_batch

    far = (0.0, 0.0, 5000.0)           # beyond reach: answered at once
    jobs = make_jobs([("airway", "far", far)], seeds=[0, 1, 2], model="physics", time_limit=5.0)
    out = tmp_path / "res"
    first = run_batch(jobs, out)
    ref = job_files_complete(out / "jobs")
    assert first.ran == 3 and len(ref) == 3
    torn = out / "jobs" / f"{jobs[1].id}.json"
    torn.write_text(torn.read_text()[:40])
    (out / "jobs" / f".{jobs[2].id}.json.abc.tmp").write_text("{")
    again = run_batch(jobs, out)
    assert (again.skipped, again.ran) == (2, 1)
    got = job_files_complete(out / "jobs")
    assert {k: without_timings(v) for k, v in got.items()} == {k: without_timings(v) for k, v in ref.items()}
    fd = os.open(out / ".lock", os.O_RDWR | os.O_CREAT)   # as another run would hold it
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        with pytest.raises(InputError, match="another plan-batch"):
            run_batch(jobs, out)
    finally:
        os.close(fd)


# ---------------------------------------------------------------------------- statistical
def _setup_inputs(tmp: Path, configs_200k: Path) -> dict[str, Path]:
    from ctrplan.cli import main

    q20k = tmp / "q20k.csv"
    with open(configs_200k) as src, open(q20k, "w") as dst:
        for k, line in enumerate(src):
            if k > 20_000:
                break
            dst.write(line)
    q1000 = tmp / "q1000.csv"
    q1000.write_text("".join(open(q20k).readlines()[:1001]))
    meas = tmp / "measured.csv"
    assert main(["-q", "simulate", "--robot", "seed1", "--configs", str(q1000), "--effect", "torsion",
                 "--noise", "0.1", "--out", str(meas)]) == 0
    return {"q200k": configs_200k, "q20k": q20k, "measured": meas}


COMMANDS = {
    # name: (argv builder (inputs, out folder), longest delay s (a lower bound of the run time))
    "shape": (lambda i, o: ["shape", "--robot", "seed1", "--configs", str(i["q200k"]),
                            "--out", str(o / "s.npz")], 5.0),
    "check": (lambda i, o: ["check", "--scene", "airway", "--robot", "seed1", "--configs",
                            str(i["q20k"]), "--out", str(o / "v.csv")], 4.0),
    "plan": (lambda i, o: ["plan", "--scene", "airway", "--target", "t02", "--out",
                           str(o / "plan.json")], 3.0),
    "plan-batch": (lambda i, o: ["plan-batch", "--targets", "examples", "--scene", "airway",
                                 "--workers", "2", "--out", str(o / "batch")], 10.0),
    "diagnose": (lambda i, o: ["diagnose", "--robot", "seed1", "--data", str(i["measured"]),
                               "--out", str(o / "report")], 4.0),
    "train": (lambda i, o: ["train", "--robot", "seed1", "--sim", "8000", "--workers", "2",
                            "--out", str(o / "m.pt")], 4.0),
}


def _assert_no_partial_output(name: str, out: Path, reference) -> None:
    """Nothing half-written: no temporary (a dot file) anywhere, and an output that exists is
    complete (the signal may come after it was renamed into place)."""
    left = [p for p in out.rglob(".*") if p.name != ".lock"]
    assert left == [], f"temporaries left: {left}"
    entries = sorted(p.name for p in out.iterdir())
    if name == "shape":
        assert entries in ([], ["s.npz"]), entries
        if entries:
            assert np.load(out / "s.npz")["points"].shape[0] == 200_000
    elif name == "check":
        assert entries in ([], ["v.csv"]), entries
        if entries:
            assert len((out / "v.csv").read_text().splitlines()) == 20_001
    elif name == "plan":
        assert entries in ([], ["plan.json"]), entries
        if entries:
            assert "success" in json.loads((out / "plan.json").read_text())
    elif name == "train":
        assert entries in ([], ["m.pt"]), entries
        if entries:
            from ctrplan.robot import load_robot
            from ctrplan.shape.models import load_model

            load_model(str(out / "m.pt"), load_robot("seed1"))
    elif name == "plan-batch":
        assert entries in ([], ["batch"]), entries
        if entries:
            jobs = job_files_complete(out / "batch" / "jobs")
            names = sorted(p.name for p in (out / "batch").iterdir() if p.name != ".lock")
            assert names in (["jobs"], []) or (
                len(jobs) == 12 and names == ["jobs", "jobs.csv", "summary.csv"]), names
    elif name == "diagnose":
        # neither a half-written report nor its temporaries beside it
        assert entries in ([], ["report"]), entries
        if entries and any((out / "report").iterdir()):
            got = sorted(p.name for p in (out / "report").iterdir())
            assert got == reference(), got
    else:  # pragma: no cover
        raise AssertionError(name)


@pytest.mark.statistical
@pytest.mark.parametrize("name", list(COMMANDS))
def test_signals_at_random_moments(tmp_path, configs_200k, name):
    """SIGINT (to the process group, as a terminal's Ctrl-C) and SIGTERM (to the command only,
    as a batch scheduler) at seeded random moments: exit 130 / 143, one line, no traceback, no
    process left in the command's session, no partial output; plan-batch then resumes."""
    inputs = _setup_inputs(tmp_path, configs_200k)
    build, longest = COMMANDS[name]
    rng = np.random.default_rng([24, len(name)])
    trials = [(signal.SIGINT, True), (signal.SIGTERM, False),
              ((signal.SIGINT, True) if rng.random() < 0.5 else (signal.SIGTERM, False))]
    stopped = 0
    ref: list[list[str]] = []

    def reference() -> list[str]:
        """The outputs of an uninterrupted run (made only when needed)."""
        if not ref:
            o = tmp_path / "reference"
            o.mkdir()
            r = subprocess.run(cli(*build(inputs, o)), cwd=tmp_path, capture_output=True, text=True,
                               env=_env(), timeout=600)
            assert r.returncode == 0, r.stderr
            ref.append(sorted(p.name for p in (o / "report").iterdir()))
        return ref[0]

    for k, (sig, group) in enumerate(trials):
        out = tmp_path / f"run{k}"
        out.mkdir()
        delay = float(rng.uniform(0.5, longest))
        run = Run(cli(*build(inputs, out)), tmp_path)
        alive, latency = run.signal_after(delay, sig, group)
        rc, err = run.finish()
        assert survivors(run.proc.pid) == [], (name, delay)
        if not alive:          # finished before the moment came: outputs complete
            assert rc == 0, err
            # on a fast (idle) machine the command ran shorter than ``longest``: later moments
            # fall within the run time just measured, so a later trial still interrupts it
            longest = max(0.6, min(longest, 0.7 * (time.monotonic() - run.started)))
            continue
        stopped += 1
        assert_stopped(rc, err, sig)
        assert latency < 10.0, (name, delay, latency)
        _assert_no_partial_output(name, out, reference)
        if name == "plan-batch" and stopped == 1:
            # resumes: the rerun finishes every job, keeping the complete ones
            done = set(job_files_complete(out / "batch" / "jobs"))
            r = subprocess.run(cli(*build(inputs, out)), cwd=tmp_path, capture_output=True,
                               text=True, env=_env(), timeout=600)
            assert r.returncode == 0, r.stderr
            assert f"({len(done)} were already done)" in r.stdout
            assert len(job_files_complete(out / "batch" / "jobs")) == 12
    assert stopped >= 1, f"{name}: every run finished before its signal"


def test_interrupt_table_is_walked():
    """Every row of the interrupt block of docs/bad-input.md names a test that exists."""
    import re

    import tests.test_batch_crash as crash

    text = (ROOT / "docs" / "bad-input.md").read_text(encoding="utf-8")
    block = text[text.index("<!-- branch intr -->"):text.index("<!-- end branch intr -->")]
    rows = re.findall(r"^\| ([a-z-]+) \|.*\| (test_[a-z0-9_]+) \|$", block, flags=re.M)
    assert len(rows) == 9
    for row, test in rows:
        assert callable(globals().get(test) or getattr(crash, test, None)), (row, test)
