"""Where Blender render workers run: a local process pool, or Ray actors on the local machine or a cluster.

An executor takes the worker init kwargs and the jobs still to render (key -> poses) and yields
`(key, frames float32 (n, H, W, 3), readback poses (n, 4, 4), scene info dict)` as views finish, in any order.
Workers only RETURN arrays; the driver (ev3dgs.sim.dataset.render_all) writes the cache and the scene file, so
the result does not depend on the executor: each worker builds the same scene from the same kwargs (seed
included) and a view's pixels depend only on the scene and its poses.

Failures reach the caller as two exception types, which render_all turns into Ev3dgsError messages:
    WorkerCrashed   a worker process died (segfault, out of memory, a lost node)
    RenderFailed    an exception raised inside a worker (bad params, bad .blend)
"""
from __future__ import annotations

import concurrent.futures as cf
import logging
import multiprocessing
import os
import socket
from collections.abc import Iterator

import numpy as np

from ..errors import Ev3dgsError, InputError

EXECUTORS = ("local", "ray")


class WorkerCrashed(Exception):
    """A render worker process died."""


class RenderFailed(Exception):
    """An exception was raised inside a render worker; the message is that exception's."""


class LocalExecutor:
    """`workers` spawned Blender processes on the local machine (concurrent.futures.ProcessPoolExecutor)."""

    def __init__(self, workers: int = 1):
        self.workers = workers

    def render(self, init_kwargs: dict, todo: dict[str, np.ndarray]) -> Iterator[tuple]:
        from ev3dgs_blender import worker

        ctx = multiprocessing.get_context("spawn")
        try:
            with cf.ProcessPoolExecutor(max_workers=self.workers, mp_context=ctx, initializer=worker.init,
                                        initargs=(init_kwargs,)) as pool:
                futures = [pool.submit(worker.render_poses, k, p) for k, p in todo.items()]
                for fut in cf.as_completed(futures):
                    yield fut.result()
        except cf.process.BrokenProcessPool:
            raise WorkerCrashed() from None
        except (ValueError, RuntimeError, OSError) as e:  # raised inside a worker (bad params, bad .blend)
            raise RenderFailed(str(e)) from None


class _BlenderActor:
    """One Ray actor = one Blender process: builds the scene once, then renders poses on request.

    An error while building the scene is kept and raised by every render call, so that it reaches the driver
    as the original exception (RenderFailed) rather than as a dead actor."""

    def __init__(self, init_kwargs: dict):
        from ev3dgs_blender import worker

        self._error = None
        try:
            worker.init(init_kwargs)
        except (ValueError, RuntimeError, OSError) as e:
            self._error = e

    def render_poses(self, key: str, poses):
        from ev3dgs_blender import worker

        if self._error is not None:
            raise self._error
        return worker.render_poses(key, poses)


class RayExecutor:
    """Blender render workers as Ray actors, on a local Ray instance or on a cluster.

    address: None starts a new local Ray instance (or uses the one this process already started); otherwise
        any address ray.init takes ("HOST:6379", "auto", "ray://HOST:10001").
    workers: number of actors (each a Blender process that builds the scene once), at most as many as the
        cluster's CPUs allow at `num_cpus` each; None = that many.
    num_cpus: CPUs Ray reserves for each actor (Cycles itself uses every core of its node).
    A Ray instance this executor started is shut down when rendering ends; one that was running is left alone.
    """

    def __init__(self, address: str | None = None, workers: int | None = None, num_cpus: float = 1,
                 quiet: bool = True):
        if workers is not None and workers < 1:
            raise InputError(f"--workers must be >= 1, got {workers}")
        self.address, self.workers, self.num_cpus, self.quiet = address, workers, num_cpus, quiet

    @staticmethod
    def _import_ray():
        try:
            import ray
        except ImportError:
            raise Ev3dgsError("the ray executor needs `pip install ev3dgs[ray]`") from None
        return ray

    def render(self, init_kwargs: dict, todo: dict[str, np.ndarray]) -> Iterator[tuple]:
        ray = self._import_ray()
        started = not ray.is_initialized()
        if started:
            _check_reachable(self.address)
            try:
                ray.init(address=self.address or "local", ignore_reinit_error=True, include_dashboard=False,
                         logging_level=logging.ERROR if self.quiet else logging.WARNING,
                         log_to_driver=not self.quiet)
            except (ConnectionError, ValueError, RuntimeError, SystemExit) as e:  # Ray exits when GCS times out
                hint = ""
                if self.address and "RAY_AUTH_MODE" not in os.environ:
                    hint = ("; a cluster with token authentication (Ray's default) needs RAY_AUTH_MODE=token "
                            "here and the head's token in RAY_AUTH_TOKEN or ~/.ray/auth_token")
                raise Ev3dgsError(f"could not start or join Ray at {self.address or 'a new local instance'}: "
                                  f"{e}{hint}") from None
        actors = []
        try:
            # more actors than the cluster has room for would never start, and their views would wait forever
            room = max(1, int(ray.cluster_resources().get("CPU", 1) // self.num_cpus))
            n = min(self.workers or room, room, len(todo))
            Actor = ray.remote(num_cpus=self.num_cpus, max_restarts=0)(_BlenderActor)
            actors = [Actor.remote(init_kwargs) for _ in range(n)]
            queue = list(todo.items())
            running = {}  # object ref -> actor
            idle = list(actors)
            while queue or running:
                while queue and idle:
                    actor = idle.pop()
                    key, poses = queue.pop(0)
                    running[actor.render_poses.remote(key, poses)] = actor
                (ref,), _ = ray.wait(list(running), num_returns=1)
                idle.append(running.pop(ref))
                try:
                    out = ray.get(ref)
                except ray.exceptions.RayActorError:
                    raise WorkerCrashed() from None
                except ray.exceptions.RayTaskError as e:
                    cause = e.cause if getattr(e, "cause", None) is not None else e
                    raise RenderFailed(str(cause)) from None
                yield out
        finally:
            for a in actors:
                try:
                    ray.kill(a)
                except Exception:  # already dead, or the cluster is gone
                    pass
            if started:
                ray.shutdown()


def _check_reachable(address: str | None, timeout_s: float = 10.0) -> None:
    """Fail fast on a HOST:PORT nobody listens at (ray.init would retry for minutes, then exit)."""
    if not address or "://" in address or address == "auto" or ":" not in address:
        return
    host, _, port = address.rpartition(":")
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s).close()
    except ValueError:
        raise InputError(f"--address must be HOST:PORT, auto or ray://HOST:PORT, got {address!r}") from None
    except OSError as e:
        raise Ev3dgsError(f"no Ray head answers at {address} ({e}); start one with `ray start --head`") from None


def make_executor(executor: str = "local", workers: int | None = 1, address: str | None = None,
                  quiet: bool = True):
    """The executor named `executor` ("local" or "ray")."""
    if executor == "local":
        if address is not None:
            raise InputError("--address needs --executor ray")
        return LocalExecutor(workers or 1)
    if executor == "ray":
        RayExecutor._import_ray()
        return RayExecutor(address=address, workers=workers, quiet=quiet)
    raise InputError(f"unknown executor {executor!r}; expected one of {', '.join(EXECUTORS)}")
