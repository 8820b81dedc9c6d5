"""The Ray backend: one Ray task per run, on an existing cluster (``address``) or on a local Ray instance
started on demand.

Each task declares ``num_cpus=threads_per_run`` (and ``num_gpus``) and runs in a fresh worker process
with the local backend's thread settings (``worker.thread_env``), so a sweep gives the same numbers on
both. A task that sees ``EXP`` (shared filesystem) writes into it; one that does not trains in a
temporary directory and ships the run's files back (``files.collect_run_files``): each new checkpoint
through an ``_Inbox`` actor while it trains, everything at the end. The driver writes them into ``EXP``, holding
the run's lock (`mcrl.run.lock`) meanwhile, as a task that writes into ``EXP`` holds it itself.

Signals: the driver's first SIGINT or SIGTERM (`mcrl.run.stop`) starts no more tasks and raises a flag in the
``_Inbox``; each running task polls it and stops its run at the next episode end with a checkpoint (shipped back
if need be), as `mcrl train` does on a signal. A second signal cancels the tasks at once.

Ray is imported only when the sweep uses it (``import_ray``), after ``ray_auth_env`` has set what Ray
reads at import time.
"""
from __future__ import annotations

import contextlib
import os
import re
import shutil
import signal
import socket
import sys
import tempfile
import threading
import time
from collections import deque
from pathlib import Path
from typing import Any

from mcrl.errors import MCRLError
from mcrl.run import lock, rundir, stop
from mcrl.sweep.driver import Driver
from mcrl.sweep.files import collect_run_files, run_dir, run_status, write_run_files
from mcrl.run.rundir import SWEEP_JSON
from mcrl.sweep.plan import RunPlan
from mcrl.sweep.worker import error_report, train_one

# Debugging / testing knob (read on the driver): "auto" (default) = a Ray worker writes into EXP when it can
# see it; "always" = every Ray run trains in a temporary directory and ships its files back; or a
# comma-separated list of run names that ship.
SHIP_ENV = "MCRL_SWEEP_SHIP_FILES"


# ------------------------------------------------------------------------------ connecting (driver)


def _probe_tcp(host: str, port: int, timeout: float = 3.0) -> str | None:
    try:
        with socket.create_connection((host, port), timeout=timeout):
            return None
    except OSError as e:
        return f"{type(e).__name__}: {e.strerror or e}"


def check_ray_address(address: str) -> None:
    """Fail fast when the GCS port of `address` (host:port or ray://host:port) does not answer."""
    if address == "auto":
        return
    m = re.fullmatch(r"(?:ray://)?\[?([^\]]+?)\]?:(\d+)", address.strip())
    if not m:
        raise MCRLError(f"--address {address!r}: give HOST:PORT of the Ray head's GCS (e.g. 10.0.0.5:6379), "
                        "ray://HOST:PORT for Ray Client, or auto")
    err = _probe_tcp(m.group(1), int(m.group(2)))
    if err:
        raise MCRLError(f"Ray cluster at {address} does not answer ({err}): start it with `ray start --head` "
                        "or fix --address; leave --address out to start a local Ray instance")


def ray_auth_env(address: str | None) -> None:
    """Ray >= 2.59: `ray start --head` enables token authentication when a token exists, but
    ray.init(address=...) sends the token only with RAY_AUTH_MODE=token, which Ray reads when it is
    imported (a cluster without authentication accepts a client that sends one)."""
    address = address or os.environ.get("RAY_ADDRESS")
    if address and address != "auto" and "RAY_AUTH_MODE" not in os.environ and "ray" not in sys.modules and (
            os.environ.get("RAY_AUTH_TOKEN") or os.environ.get("RAY_AUTH_TOKEN_PATH")
            or (Path.home() / ".ray" / "auth_token").is_file()):
        os.environ["RAY_AUTH_MODE"] = "token"


def import_ray():
    try:
        import ray
    except ImportError:
        raise MCRLError("--backend ray needs Ray: pip install 'mcrl[sweep]' (or 'ray[default]')") from None
    return ray


def start_ray(address: str | None, cpus: int):
    """Connect to `address`, or start a local Ray instance with `cpus` CPUs. Returns (ray, started_local)."""
    import logging

    ray = import_ray()
    address = address or os.environ.get("RAY_ADDRESS") or None
    if address:
        check_ray_address(address)
    try:
        if address:
            ray.init(address=address, log_to_driver=False, logging_level=logging.WARNING)
        else:
            # address="local": a new instance even when `ray start` left one (or its stale address file) behind
            ray.init(address="local", num_cpus=cpus, include_dashboard=False, log_to_driver=False,
                     logging_level=logging.WARNING)
    except (ConnectionError, TimeoutError, RuntimeError, ValueError) as e:
        first = str(e).strip().splitlines()[0] if str(e).strip() else ""
        where = f"the Ray cluster at {address}" if address else "a local Ray instance"
        raise MCRLError(f"cannot connect to {where} ({type(e).__name__}: {first}): start the cluster with "
                        "`ray start --head` or fix --address (a cluster with token authentication also needs "
                        "its token: RAY_AUTH_TOKEN or ~/.ray/auth_token)") from None
    return ray, not address


# ------------------------------------------------------------------------------ the worker side


class _Inbox:
    """Ray actor: messages from the tasks to the driver (run started, checkpoint files)."""

    def __init__(self):
        self.msgs: list = []
        self.stop = False  # the driver asks the running tasks to save and stop

    def request_stop(self) -> bool:
        self.stop = True
        return True

    def stopping(self) -> bool:
        return self.stop

    def push(self, msg) -> bool:
        self.msgs.append(msg)
        return True

    def drain(self) -> list:
        out, self.msgs = self.msgs, []
        return out


def _sees_experiment(spec: dict[str, Any]) -> bool:
    """Whether this worker sees the driver's EXP (the same sweep id in sweep.json) and may write into it."""
    d = rundir.read_json(Path(spec["exp"]) / SWEEP_JSON)
    return d.get("id") == spec["sweep_id"] and os.access(spec["exp"], os.W_OK)


def _ray_task(spec: dict[str, Any], inbox, seed_box: list, force_ship: bool) -> dict[str, Any]:
    """One run as a Ray task (runs in a fresh worker whose thread env vars came with the task)."""
    import ray

    if ray.get(inbox.stopping.remote()):
        return {"stopped": None}
    lock.describe_holder(f"a Ray task of `mcrl sweep --exp {spec['exp']}`")
    shared = not force_ship and _sees_experiment(spec)
    ray.get(inbox.push.remote(("start", spec["name"], os.getpid(), socket.gethostname(), shared)))
    done = threading.Event()

    def watch_for_stop():  # the driver's stop request, as a signal would make it
        while not done.wait(1.0):
            with contextlib.suppress(Exception):
                if ray.get(inbox.stopping.remote()):
                    stop.request()
                    return

    threading.Thread(target=watch_for_stop, daemon=True).start()
    try:
        if shared:
            with stop.handle(second_stops_now=False):
                return {"summary": train_one(spec["config"], spec["run_dir"])}
        tmp = Path(tempfile.mkdtemp(prefix="mcrl-sweep-"))
        rdir = tmp / spec["name"]
        try:
            seed = ray.get(seed_box[0]) if seed_box else None
            if seed:
                write_run_files(rdir, seed, keep=int(spec["config"]["keep_checkpoints"]))
            shipping_done = threading.Event()

            def ship_checkpoints():  # send every new checkpoint (and the CSVs up to it) to the driver
                sent = None
                while not shipping_done.wait(1.0):
                    try:
                        latest = rundir.latest_checkpoint(rdir)
                        if latest is not None and latest != sent:
                            files = collect_run_files(rdir, final=False)
                            ray.get(inbox.push.remote(("files", spec["name"], files)))
                            sent = latest
                    except OSError:
                        continue  # a checkpoint being replaced: next time

            watcher = threading.Thread(target=ship_checkpoints, daemon=True)
            watcher.start()
            try:
                with stop.handle(second_stops_now=False):
                    summary = train_one(spec["config"], rdir)
            except stop.Stopped as e:
                ((_, step),) = e.saved
                return {"stopped": step, "files": collect_run_files(rdir, final=False)}
            finally:
                shipping_done.set()
                watcher.join()
            return {"summary": summary, "files": collect_run_files(rdir, final=True)}
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    except stop.Stopped as e:
        ((_, step),) = e.saved
        return {"stopped": step}
    except MCRLError as e:
        return {"error": str(e)}
    except Exception as e:
        why, tb = error_report(e)
        return {"error": why, "traceback": tb}
    finally:
        done.set()


# ------------------------------------------------------------------------------ the driver side


def run_ray(ray, todo: list[RunPlan], exp: Path, sweep_id: str, limit: int, threads: int, gpus: float,
            env: dict[str, str], retries: int, local_instance: bool, drv: Driver) -> None:
    """Run `todo` as Ray tasks, at most `limit` at a time, reporting each run's end to `drv`."""
    ship_knob = os.environ.get(SHIP_ENV, "auto").strip() or "auto"
    ship_names = None if ship_knob in ("auto", "always") else {s.strip() for s in ship_knob.split(",")}

    def forced(name: str) -> bool:
        return ship_knob == "always" or (ship_names is not None and name in ship_names)

    inbox = ray.remote(num_cpus=0)(_Inbox).remote()
    # max_calls=1: a fresh worker process per run (its thread settings from the first instruction on, and
    # its memory returned when the run ends)
    task = ray.remote(max_calls=1)(_ray_task).options(num_cpus=threads, num_gpus=gpus or 0, max_retries=retries,
                                                      runtime_env={"env_vars": env})
    queue = deque(todo)
    inflight: dict[Any, tuple] = {}  # ref -> (run, t0, seed ref)
    by_name: dict[str, RunPlan] = {r.name: r for r in todo}
    locks: dict[str, lock.RunLock] = {}  # runs whose files this driver writes (their tasks ship them back)
    stopping = False
    try:
        while queue or inflight:
            if stop.requested() is not None and not stopping:  # first SIGINT/SIGTERM: the runs save and stop
                stopping = True
                queue.clear()
                drv.line(f"{signal.Signals(stop.requested()).name}: each running run saves a checkpoint at its "
                         "episode's end, then the sweep stops (press Ctrl-C again to stop at once)")
                ray.get(inbox.request_stop.remote())
                if not inflight:
                    break
            while queue and len(inflight) < limit:
                run = queue.popleft()
                rdir = run_dir(exp, run.name)
                state, step = run_status(rdir)
                seed_box = []
                if state == "checkpoint" and (forced(run.name) or not local_instance):
                    seed_box = [ray.put(collect_run_files(rdir, final=False))]  # fetched only if needed
                spec = {"name": run.name, "config": run.config.to_dict(), "run_dir": str(rdir),
                        "exp": str(exp), "sweep_id": sweep_id}
                ref = task.remote(spec, inbox, seed_box, forced(run.name))
                inflight[ref] = (run, time.monotonic(), seed_box)
                drv.set_steps(run.name, step)
                how = f" (resumes from step {step})" if state == "checkpoint" else ""
                drv.line(f"{drv.tag()} queued {run.name}{how}")
            ready, _ = ray.wait(list(inflight), num_returns=len(inflight), timeout=1.0)
            for msg in ray.get(inbox.drain.remote()):  # after wait: a finished task's messages are all in
                if msg[0] == "start":
                    _, name, pid, host, shared = msg
                    drv.line(f"{drv.tag()} start {name} (pid {pid} on {host}"
                             f"{'' if shared else ', files shipped back'})")
                    if not shared and name not in locks:  # (a retried task starts again: locked already)
                        try:
                            locks[name] = lock.acquire(run_dir(exp, name))
                        except MCRLError as e:  # someone else writes the run: it cannot be shipped into it
                            ref = next(r for r, (run, *_) in inflight.items() if run.name == name)
                            with contextlib.suppress(Exception):
                                ray.cancel(ref, force=True)
                            inflight.pop(ref)
                            drv.failed(name, str(e))
                elif msg[0] == "files" and msg[1] in locks:
                    _, name, files = msg
                    write_run_files(run_dir(exp, name), files, by_name[name].config.keep_checkpoints)
                    drv.set_steps(name, run_status(run_dir(exp, name))[1])
            for ref in ready:
                if ref not in inflight:  # cancelled above
                    continue
                run, t0, _seed = inflight.pop(ref)
                held = locks.pop(run.name, None)
                try:
                    _finish(ray, ref, run, t0, exp, drv)
                finally:
                    if held is not None:
                        held.release()
            drv.poll([r.name for r, *_ in inflight.values()])
    finally:
        for ref in inflight:
            with contextlib.suppress(Exception):
                ray.cancel(ref, force=True)
        with contextlib.suppress(Exception):
            ray.kill(inbox)
        for held in locks.values():
            held.release()


def _finish(ray, ref, run: RunPlan, t0: float, exp: Path, drv: Driver) -> None:
    """Report the end of `run`'s task `ref` to `drv`, writing the files it shipped back."""
    try:
        out = ray.get(ref)
    except Exception as e:  # the worker died (killed, out of memory, node lost) after its retries
        first = str(e).strip().splitlines()[0] if str(e).strip() else ""
        drv.failed(run.name, f"{type(e).__name__}: {first}"[:300])
        return
    if "error" in out:
        drv.failed(run.name, out["error"], out.get("traceback"))
        return
    if "files" in out:
        write_run_files(run_dir(exp, run.name), out["files"], run.config.keep_checkpoints)
    if "stopped" in out:
        drv.stopped(run.name, out["stopped"])
    else:
        drv.done(run, t0, out["summary"])
