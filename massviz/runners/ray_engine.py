"""The Ray engine of ``massviz.runners.dataset.run_dataset`` (imported only for ``--engine ray``; ``massviz[ray]``).

* Connection: ``address=None`` starts a local Ray instance with this machine's cores (no dashboard, every Ray
  server bound to 127.0.0.1) and shuts it down at the end; ``"auto"`` joins the cluster this machine belongs to
  (``ray start --head`` / ``ray start --address``); ``HOST:PORT`` joins that cluster's head. An address where no
  Ray answers within ``CONNECT_TIMEOUT_S`` (10 s) is one line naming --ray-address (``check_address``), not Ray's
  endless retries. A Ray already initialised in this process (a notebook, the tests) is used as it is and left
  running.
* Workers: a pool of ``RayWorker`` actors; each builds the pipeline once (detector and mass-CNN weights loaded once
  per actor). With GPUs in the cluster: one actor per GPU (``num_gpus=1``) unless ``workers`` says otherwise; else
  ``workers`` CPU actors (default: one per CPU) sharing the CPUs (torch threads per actor = CPUs // actors).
* One Ray task (actor call) per recording; the actor opens the recording from its path (shared storage; frames are
  never shipped from the driver), writes the trace to the trace cache and returns a small ``Outcome``.
* Faults: the process of an actor that dies is restarted by Ray and the calls it had are retried (``MAX_RETRIES``
  times each); a recording whose actor has no restart left is tried once more on another actor, then fails with
  "the Ray worker processing it died".

Why not ``ray.util.ActorPool`` (checked on Ray 2.60): when a call fails, ``get_next_unordered`` raises
without saying which value it was for, so the recording could neither be retried on another actor nor named in
its failure line; an actor whose process died stays out of the pool but the values queued for it stay in the pool's
private ``_pending_submits`` (``has_next()`` is then False: they would be silently dropped instead of reported
"not run: every Ray worker died"); and it keeps one call per actor in flight (:data:`IN_FLIGHT` is 2 here, so an
actor never waits a round trip for its next recording). ``_dispatch`` is the ~40 lines that keep those three.
"""
from __future__ import annotations

import logging
import os
import re
import sys
import time
from collections import deque

from massviz.errors import MassvizError
from massviz.io.endpoint import CONNECT_TIMEOUT_S, host_port, reach_grpc
from massviz.runners.worker import FAULT_ENV, Outcome, RecordingWorker

_LOG = logging.getLogger(__name__)

#: restarts of a dead actor process, and retries of each call it was running, that Ray makes.
MAX_RETRIES = 3
#: calls kept in flight per actor (the next one waits on the actor while one runs: no idle round trip).
IN_FLIGHT = 2
#: set (unless already set) before Ray is imported when massviz starts its own local instance: Ray then takes
#: 127.0.0.1 as the node address and binds its servers there, not on every interface.
LOCAL_ONLY_ENV = "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"


def import_ray(local: bool):
    if local and "ray" not in sys.modules:
        os.environ.setdefault(LOCAL_ONLY_ENV, "0")
    try:
        import ray
    except ImportError:
        raise MassvizError("--engine ray needs Ray: pip install 'massviz[ray]'") from None
    return ray


#: what to do when nothing answers at --ray-address.
ADDRESS_HINT = ("pass --ray-address HOST:PORT of a running cluster (`ray start --head` starts one), or leave "
                "--ray-address out to start a local Ray instance")


def check_address(address: str, timeout: float = CONNECT_TIMEOUT_S) -> None:
    """Before ``ray.init`` (which waits on an address where nothing answers for as long as it is left running): the
    address Ray would connect to for ``address`` (``auto``: the cluster this machine runs; ``ray://``: a Ray Client
    server) answers as a gRPC server within ``timeout`` seconds, else one ``MassvizError`` naming --ray-address."""
    from ray._private.services import canonicalize_bootstrap_address

    target = address
    if not address.startswith("ray://"):
        try:
            target = canonicalize_bootstrap_address(address) or address
        except Exception:  # noqa: BLE001 - "auto" with no cluster, a malformed address: ray.init says why
            return
    host, port = host_port(target, "--ray-address")
    reach_grpc("--ray-address", address, host, port, timeout, ADDRESS_HINT)


def connect(address: str | None, log=None, timeout: float = CONNECT_TIMEOUT_S):
    """(the ray module, whether this call started or joined Ray and must shut it down). Joining ``address`` waits
    at most ``timeout`` seconds for it to answer (``check_address``)."""
    ray = import_ray(local=address is None)
    if ray.is_initialized():
        return ray, False
    t0 = time.perf_counter()
    if address is not None:
        check_address(address, timeout)
    for attempt in (1, 2):  # Ray gives its raylet 30 s to register (hard-coded): a loaded machine may need a retry
        try:
            if address is None:
                ray.init(num_cpus=os.cpu_count() or 1, include_dashboard=False, logging_level="WARNING")
            else:
                ray.init(address=address, logging_level="WARNING")
            break
        except Exception as err:  # noqa: BLE001 - Ray raises bare Exception, RuntimeError, ConnectionError, ...
            ray.shutdown()
            first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
            if attempt == 1 and address is None and "timed out" in first:
                if log is not None:
                    log(f"massviz: Ray did not start in time ({first}); trying once more")
                continue
            if address is None:
                raise MassvizError(f"cannot start a local Ray instance: {first}") from None
            # Ray's own advice names Ray's options (its `--address` flag, RAY_ADDRESS), not massviz's --ray-address
            first = re.sub(r"\.?\s*Please specify[^.]*`?--address`?[^.]*\.?", "", first)
            first = first.replace("--address", "--ray-address")
            raise MassvizError(f"cannot join the Ray cluster at {address}: {first.rstrip('.')}. "
                               f"{ADDRESS_HINT[0].upper()}{ADDRESS_HINT[1:]}") from None
    if log is not None:
        res = ray.cluster_resources()
        what = "started a local Ray instance" if address is None else f"joined the Ray cluster at {address}"
        log(f"massviz: {what} ({int(res.get('CPU', 0))} CPUs, {int(res.get('GPU', 0))} GPUs) in "
            f"{time.perf_counter() - t0:.1f} s")
    return ray, True


class RayWorker(RecordingWorker):
    """A ``RecordingWorker`` living in a Ray actor; ``fault_id``: the test-only hook (``FAULT_ENV``)."""

    def __init__(self, options, threads, fault_id: str | None = None):
        super().__init__(options, None, threads)
        self.fault_id = fault_id

    def process(self, task, collect) -> Outcome:
        return self.run(task, collect=collect, fault=self._fault if self.fault_id else None)

    def _fault(self, recording) -> None:
        """Die (the whole worker process, as a crash would) in the middle of the recording the hook names, once:
        the restarted actor (``was_current_actor_reconstructed``) goes on."""
        import ray

        if recording.id == self.fault_id and not ray.get_runtime_context().was_current_actor_reconstructed:
            for _ in recording.frames(indices=[0]):
                pass
            os._exit(1)


def plan(resources: dict, workers: int | None, threads: int | None) -> tuple[int, dict, int]:
    """(number of actors, the Ray resources of each, torch threads of each) for the cluster's ``resources``."""
    gpus, cpus = float(resources.get("GPU", 0)), max(float(resources.get("CPU", 1)), 1.0)
    if gpus >= 1:
        n = workers or int(gpus)
        return n, {"num_gpus": min(1.0, gpus / n), "num_cpus": min(1.0, cpus / n)}, threads or max(1, int(cpus // n))
    n = workers or int(cpus)
    per_actor = cpus / n if n > cpus else float(int(cpus // n))  # fractional when there are more actors than CPUs
    return n, {"num_cpus": per_actor}, threads or max(1, int(cpus // n))


#: opt-in (``=1``): keep the actor pool after a run in a Ray this module did not start (a notebook's, the tests'), so
#: a next run with the same pipeline options starts at once. Off by default: a kept pool holds the cluster's CPUs, and
#: another driver's run would wait for them. One pool at most (a run with other options kills it first); free it
#: with ``release_pools()``.
KEEP_ENV = "MASSVIZ_RAY_KEEP_WORKERS"
_POOLS: dict = {}  # (options, threads, actors, resources, fault hook) -> actors


def run_ray(tasks, options, collect, *, workers=None, threads=None, address=None, record, log=None,
            stats=None) -> None:
    """Run ``tasks`` on a pool of Ray actors; ``record(outcome)`` is called on the driver as results arrive (it may
    raise to stop the run). KeyboardInterrupt: the actors are killed and Ray shut down (if this call started it)."""
    stats = {} if stats is None else stats
    t0 = time.perf_counter()
    ray, started = connect(address, log)
    actors: list = []
    keep = False
    try:
        n, resources, nthreads = plan(ray.cluster_resources(), workers, threads)
        n = max(1, min(n, len(tasks)))
        fault = os.environ.get(FAULT_ENV) or None
        key = (options, nthreads, n, tuple(sorted(resources.items())), fault)
        actors = [] if started else _POOLS.pop(key, [])
        if not actors:
            release_pools()
            remote = ray.remote(max_restarts=MAX_RETRIES, max_task_retries=MAX_RETRIES)(RayWorker)
            actors = [remote.options(**resources).remote(options, nthreads, fault) for _ in range(n)]
        try:  # wait for every actor to have built its pipeline: a worker that cannot start is one clear error
            _wait(ray, [a.ready.remote() for a in actors], log, f"massviz: still waiting for Ray to place {n} "
                  f"worker(s) of {resources}; is the cluster busy?")
        except ray.exceptions.RayActorError as err:
            raise MassvizError(f"a Ray worker could not start: {_cause(err)}") from None
        stats.update(workers=n, threads=nthreads, resources=resources, startup_s=time.perf_counter() - t0)
        if log is not None:
            log(f"massviz: {n} Ray worker(s) ready ({nthreads} torch thread(s) each) in "
                f"{time.perf_counter() - t0:.1f} s")
        keep = (_dispatch(ray, actors, tasks, record, collect) and not started
                and os.environ.get(KEEP_ENV) == "1")
        if keep:
            _POOLS[key] = actors
    finally:
        if not keep:
            for actor in actors:
                try:
                    ray.kill(actor, no_restart=True)
                except Exception:  # noqa: BLE001 - already dead, or Ray going down
                    pass
        if started:
            ray.shutdown()


def release_pools() -> None:
    """Kill the actor pools kept between runs (``_POOLS``); call before ``ray.shutdown()`` of your own Ray."""
    import ray

    while _POOLS:
        for actor in _POOLS.popitem()[1]:
            try:
                ray.kill(actor, no_restart=True)
            except Exception:  # noqa: BLE001
                pass


def _wait(ray, refs, log=None, slow: str = "", after: float = 60.0):
    """``ray.get`` in short waits, so that Ctrl-C is seen at once (``slow`` is logged once after ``after`` s)."""
    pending, t0 = list(refs), time.monotonic()
    while pending:
        _, pending = ray.wait(pending, num_returns=len(pending), timeout=0.5)
        if pending and slow and time.monotonic() - t0 > after:
            (log or _LOG.warning)(slow)
            slow = ""
    return ray.get(list(refs))


def _cause(err) -> str:
    lines = [ln.strip() for ln in str(err).strip().splitlines() if ln.strip()]
    for ln in reversed(lines):  # the worker's own error line (e.g. massviz.errors.WeightsError: ...) when there
        if "Error:" in ln or "Error " in ln:
            return ln
    return lines[0] if lines else type(err).__name__


def _dispatch(ray, actors, tasks, record, collect) -> bool:
    """Keep every actor busy until every task has an outcome; True when every actor is still alive."""
    queue = deque(tasks)
    tries: dict[int, int] = {}
    inflight: dict = {}  # ObjectRef -> (actor, task)
    alive = list(actors)

    def submit(actor) -> None:
        if queue:
            task = queue.popleft()
            inflight[actor.process.remote(task, collect)] = (actor, task)

    for _ in range(IN_FLIGHT):
        for actor in alive:
            submit(actor)
    while inflight:
        ready, _ = ray.wait(list(inflight), num_returns=1, timeout=0.5)
        for ref in ready:
            actor, task = inflight.pop(ref)
            try:
                outcome = ray.get(ref)
            except ray.exceptions.RayActorError as err:  # the actor is gone for good (its restarts used up)
                if actor in alive:
                    alive.remove(actor)
                tries[task.index] = tries.get(task.index, 0) + 1
                if tries[task.index] < 2 and alive:
                    queue.appendleft(task)
                    submit(alive[task.index % len(alive)])
                    continue
                outcome = Outcome(task.index, task.id, task.path, "failed", internal=True,
                                  error=f"{task.path}: the Ray worker processing it died ({MAX_RETRIES} restarts "
                                  f"used): {_cause(err)}")
            except ray.exceptions.RayTaskError as err:  # an exception the worker did not turn into an outcome
                outcome = Outcome(task.index, task.id, task.path, "failed", internal=True,
                                  error=f"{task.path}: internal error: {_cause(err)}")
            record(outcome)
            if actor in alive:
                submit(actor)
        if not alive and queue:
            while queue:
                task = queue.popleft()
                record(Outcome(task.index, task.id, task.path, "failed", internal=True,
                               error=f"{task.path}: not run: every Ray worker died"))
    return len(alive) == len(actors)


__all__ = ["MAX_RETRIES", "LOCAL_ONLY_ENV", "KEEP_ENV", "RayWorker", "check_address", "connect", "plan", "release_pools", "run_ray"]
