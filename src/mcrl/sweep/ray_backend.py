"""The Ray backend (`RayBackend`): one Ray task per run, on an existing cluster (``address``) or on a local Ray
instance started on demand.

Each task declares ``num_cpus=threads`` (and ``num_gpus``) and runs in a fresh worker process with the local
backend's settings: ``worker.thread_env`` and, with ``--threads-per-run N``, pinned to N cores of its slot
(``worker.pin_cores``: exact on a local instance; on a cluster's node the slot's cores may overlap another task's,
the count and so the numbers are right), so a sweep gives the same numbers on both. A task that sees ``EXP``
(shared filesystem) writes into it; one that does not trains in a temporary directory and ships the run's files back
(``files.collect_run_files``): each new checkpoint through an ``_Inbox`` actor while it trains, everything at the
end. The driver writes them into ``EXP``, holding the run's lock (`mcrl.run.lock`) meanwhile, as a task that
writes into ``EXP`` holds it itself.

A stop request (`request_stop`) raises a flag in the ``_Inbox``; each running task polls it and stops its run at
the next episode end with a checkpoint (shipped back if need be), as `mcrl train` does on a signal. A task
returns its job's `Outcome` (`mcrl.sweep.backend`) and the files it ships. ``close()`` stops the tasks still
running the same way and waits for them, writing what they ship; ``close(kill=True)`` cancels them at once
(``ray.cancel(force=True)``: each run keeps its last periodic checkpoint). A task whose worker died (killed, node
lost) ends as "died", and the driver (`mcrl.sweep.driver.drive`) starts it again if retries are left (Ray's own
retries are off).

Ray is imported only when the sweep uses it (``import_ray``), after ``ray_auth_env`` has set what Ray
reads at import time.
"""
from __future__ import annotations

import contextlib
import os
import re
import shutil
import socket
import sys
import tempfile
import threading
from pathlib import Path
from typing import Any, ClassVar

from mcrl.errors import MCRLError
from mcrl.run import lock, rundir, stop
from mcrl.run.rundir import SWEEP_JSON
from mcrl.sweep.backend import Ended, Job, Outcome, Settings, Started
from mcrl.sweep.files import collect_run_files, run_dir, run_status, write_run_files
from mcrl.sweep.plan import RunPlan
from mcrl.sweep.worker import outcome_of, pin_cores, train_one

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


def _ray_task(spec: dict[str, Any], inbox, seed_box: list,
              force_ship: bool) -> tuple[Outcome, dict[str, bytes] | None]:
    """One run as a Ray task (runs in a fresh worker whose thread env vars came with the task): its `Outcome`,
    and the run's files when it trained in a temporary directory (else None)."""
    if spec["pin"]:
        pin_cores(spec["threads"], spec["slot"])  # before train_one imports jax
    import ray

    name = spec["name"]
    if ray.get(inbox.stopping.remote()):
        return Outcome("stopped", {name: None}), None
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
                return Outcome("ok", {name: train_one(spec["config"], spec["run_dir"])}), None
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
                return outcome_of(e, {name: rdir}), collect_run_files(rdir, final=False)
            finally:
                shipping_done.set()
                watcher.join()
            return Outcome("ok", {name: summary}), collect_run_files(rdir, final=True)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    except (stop.Stopped, Exception) as e:  # stopped, locked or failed (a cancelled task's interrupt goes on)
        return outcome_of(e, {name: spec["run_dir"]}), None
    finally:
        done.set()


# ------------------------------------------------------------------------------ the driver side


class RayBackend:
    """A Ray task per run (see the module's docstring)."""

    name: ClassVar[str] = "ray"
    # --address: the cluster (None: a local instance); --gpus-per-run: the GPUs each task asks for
    OPTIONS: ClassVar[dict[str, Any]] = {"address": None, "gpus_per_run": 0.0}

    def __init__(self, settings: Settings):
        self.s = settings
        self.options = {**self.OPTIONS, **settings.options}
        self.ray, self.local_instance = start_ray(self.options["address"], settings.workers * settings.threads)
        ray = self.ray
        if settings.workers_given:
            self.slots = settings.workers
        else:  # as many as the cluster's CPUs allow
            cpus = float(ray.cluster_resources().get("CPU", settings.workers * settings.threads))
            self.slots = max(1, int(cpus // settings.threads))
        knob = os.environ.get(SHIP_ENV, "auto").strip() or "auto"
        self._ship_all = knob == "always"
        self._ship_names = None if knob in ("auto", "always") else {n.strip() for n in knob.split(",")}
        self._inbox = ray.remote(num_cpus=0)(_Inbox).remote()
        # max_calls=1: a fresh worker process per run (its cores and thread settings from the first instruction
        # on, and its memory returned when the run ends); retries are the driver's
        self._task = ray.remote(max_calls=1)(_ray_task).options(
            num_cpus=settings.threads, num_gpus=self.options["gpus_per_run"] or 0, max_retries=0,
            runtime_env={"env_vars": settings.env})
        self._inflight: dict[Any, tuple[Job, int]] = {}  # ref -> (job, slot)
        self._locks: dict[str, lock.RunLock] = {}  # runs whose files this driver writes (their tasks ship them)

    @classmethod
    def default_workers(cls, cores: int) -> int:
        return cores

    @classmethod
    def check_options(cls, options: dict[str, Any]) -> None:
        if options["gpus_per_run"] < 0:
            raise MCRLError(f"--gpus-per-run {options['gpus_per_run']}: give 0 or more")

    @classmethod
    def check(cls, settings: Settings) -> None:
        address = settings.options.get("address")
        if address:
            check_ray_address(address)
        ray_auth_env(address)
        import_ray()

    def jobs(self, todo: list[RunPlan]) -> list[list[RunPlan]]:
        return [[r] for r in todo]

    def _forced(self, name: str) -> bool:
        return self._ship_all or (self._ship_names is not None and name in self._ship_names)

    def launch(self, job: Job) -> None:
        (run,) = job.runs
        rdir = run_dir(self.s.exp, run.name)
        used = {slot for _, slot in self._inflight.values()}
        slot = next(i for i in range(len(self._inflight) + 1) if i not in used)
        seed_box = []
        if run_status(rdir)[0] == "checkpoint" and (self._forced(run.name) or not self.local_instance):
            seed_box = [self.ray.put(collect_run_files(rdir, final=False))]  # fetched only if needed
        spec = {"name": run.name, "config": run.config.to_dict(), "run_dir": str(rdir), "exp": str(self.s.exp),
                "sweep_id": self.s.sweep_id, "threads": self.s.threads, "pin": self.s.pin, "slot": slot}
        ref = self._task.remote(spec, self._inbox, seed_box, self._forced(run.name))
        self._inflight[ref] = (job, slot)
        return None  # it says where when its task starts

    def poll(self, timeout: float) -> list[Started | Ended]:
        ray, out = self.ray, []
        if not self._inflight:
            return out
        ready, _ = ray.wait(list(self._inflight), num_returns=len(self._inflight), timeout=timeout)
        by_name = {job.runs[0].name: (ref, job) for ref, (job, _) in self._inflight.items()}
        for msg in ray.get(self._inbox.drain.remote()):  # after wait: a finished task's messages are all in
            if msg[1] not in by_name:
                continue
            ref, job = by_name[msg[1]]
            if msg[0] == "start":
                _, name, pid, host, shared = msg
                out.append(Started(job, f"pid {pid} on {host}{'' if shared else ', files shipped back'}"))
                if not shared and name not in self._locks:  # (a retried task starts again: locked already)
                    try:
                        self._locks[name] = lock.acquire(run_dir(self.s.exp, name))
                    except lock.Locked as e:  # someone else writes the run: it cannot be shipped into it
                        with contextlib.suppress(Exception):
                            ray.cancel(ref, force=True)
                        self._inflight.pop(ref)
                        out.append(Ended(job, Outcome("locked", {name: None}, holder=e.holder)))
            elif msg[0] == "files" and msg[1] in self._locks:
                write_run_files(run_dir(self.s.exp, msg[1]), msg[2], job.runs[0].config.keep_checkpoints)
        for ref in ready:
            if ref not in self._inflight:  # cancelled above
                continue
            job, _ = self._inflight.pop(ref)
            held = self._locks.pop(job.runs[0].name, None)
            try:
                out.append(self._ended(ref, job))
            finally:
                if held is not None:
                    held.release()
        return out

    def _ended(self, ref, job: Job) -> Ended:
        """The end of `job`'s task `ref`, the files it shipped back written into EXP."""
        (run,) = job.runs
        try:
            outcome, files = self.ray.get(ref)
        except Exception as e:  # the worker died (killed, out of memory, node lost)
            first = str(e).strip().splitlines()[0] if str(e).strip() else ""
            return Ended(job, Outcome("died", why=f"{type(e).__name__}: {first}"[:300]))
        if files is not None:
            write_run_files(run_dir(self.s.exp, run.name), files, run.config.keep_checkpoints)
        return Ended(job, outcome)

    def request_stop(self) -> None:
        self.ray.get(self._inbox.request_stop.remote())

    def close(self, kill: bool = False) -> None:
        """Stop the running tasks (each run saves at its episode's end; shipped files are written into EXP) and
        wait for them; with `kill`, or if the stop fails or is interrupted, cancel them at once. Then Ray ends."""
        if self.ray is None:
            return
        try:
            if not kill and self._inflight:
                self.request_stop()
                while self._inflight:
                    self.poll(1.0)
        except Exception:  # the sweep's own error, if any, stays the error: what is left is cancelled below
            pass
        finally:
            for ref in self._inflight:
                with contextlib.suppress(Exception):
                    self.ray.cancel(ref, force=True)
            with contextlib.suppress(Exception):
                self.ray.kill(self._inbox)
            for held in self._locks.values():
                held.release()
            self._inflight.clear()
            self._locks.clear()
            with contextlib.suppress(Exception):
                self.ray.shutdown()
            self.ray = None
