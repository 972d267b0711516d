"""`cuboidtrain serve`: the page's settings, its pool of fitting processes, and the server's run.

Fits run in `workers` processes (`FitPool`), never on the server's event loop: each worker
comes from `infer --workers`' fork server (`infer.pool.worker_context`: torch imported once,
Ctrl-C ignored), holds the shipped models and fits on one torch thread, so the page's numbers
are `infer`'s to the last bit, and two users at once each get their own answer while the
server goes on answering. uvicorn serves the app (`app.make_app`) on 127.0.0.1 unless told
otherwise; Ctrl-C (or SIGTERM) stops it after the answers in flight, and the pool with it.
"""
from __future__ import annotations

import asyncio
import ipaddress
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass

from shared.checks import check_numbers, number
from shared.errors import UsageError

DEFAULT_PORT = 8765


@dataclass(frozen=True)
class ServeConfig:
    """What `cuboidtrain serve` is asked (its options, one to one)."""

    host: str = "127.0.0.1"  # the address to listen on: this machine only, unless told
    port: int = number(DEFAULT_PORT, lo=1, hi=65535, integer=True)
    workers: int = number(2, lo=1, hi=64, integer=True)  # fitting processes: answers at once
    max_upload_mb: float = number(32.0, lo=0, lo_open=True, hi=1024)  # MB (10^6 bytes): a larger upload is refused

    def validate(self) -> "ServeConfig":
        check_numbers(self)
        try:
            ipaddress.ip_address(self.host)
        except ValueError:
            if self.host != "localhost":
                raise UsageError(f"--host {self.host!r}: expected an IP address (127.0.0.1, 0.0.0.0, ::1) "
                                 f"or localhost") from None
        return self

    @property
    def max_upload_bytes(self) -> int:
        return int(self.max_upload_mb * 1e6)

    @property
    def address(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}/"


class FitPool:
    """The worker processes: `await pool.run(fn, *args)` runs `fn` in one of them. A worker that dies
    (killed, out of memory) fails the answers in flight with a one-line error, and a fresh pool
    takes the next ones: the server goes on."""

    def __init__(self, workers: int):
        self.workers = workers
        self.executor = self._start()

    def _start(self) -> ProcessPoolExecutor:
        from cuboidtrain.infer.pool import worker_context
        from cuboidtrain.web.answer import start_worker

        return ProcessPoolExecutor(self.workers, mp_context=worker_context(), initializer=start_worker)

    async def warm_up(self) -> None:
        """Start every worker and wait until each holds its models: the first answer is a warm one."""
        from cuboidtrain.web.answer import ready

        assert all(await asyncio.gather(*(self.run(ready) for _ in range(self.workers))))

    async def run(self, fn, *args):
        executor = self.executor
        try:
            return await asyncio.wrap_future(executor.submit(fn, *args))
        except BrokenProcessPool:
            if executor is self.executor:  # the first answer to see it starts the fresh pool
                self.executor = self._start()
                executor.shutdown(wait=False, cancel_futures=True)
            raise UsageError("a fitting process died during this fit (out of memory?); the page goes on: "
                             "try again, or fit the file with cuboidtrain infer") from None

    def close(self) -> None:
        self.executor.shutdown(wait=True, cancel_futures=True)


def serve(config: ServeConfig, announce=print) -> None:
    """Serve the page until Ctrl-C or SIGTERM; `announce` gets the line with its address once the
    workers are warm."""
    config = config.validate()
    require_web()
    import uvicorn

    from cuboidtrain.web.app import make_app

    pool = FitPool(config.workers)
    server = announcing_server(uvicorn, make_app(config, pool), config,
                               lambda: announce(f"cuboid-fit page at {config.address} (Ctrl-C stops it)"))
    try:
        server.run()
    except KeyboardInterrupt:  # uvicorn hands Ctrl-C back once it has shut down
        pass
    if not server.started:
        raise UsageError(f"--host {config.host} --port {config.port}: could not serve there (in use, or not "
                         f"this machine's address)")


def announcing_server(uvicorn, app, config: ServeConfig, announce):
    """uvicorn's server for `app`, calling `announce` once it listens. Its lifespan (the workers'
    warm-up) runs before the socket is bound, so an address said there could still be refused: a
    test that posted at once met "Connection refused"."""

    class Announcing(uvicorn.Server):
        async def startup(self, sockets=None) -> None:
            await super().startup(sockets=sockets)
            if self.started:  # bound and listening (uvicorn sets it last)
                announce()

    return Announcing(uvicorn.Config(app, host=config.host, port=config.port, log_level="warning",
                                     access_log=False, lifespan="on"))


WEB_MODULES = ("starlette", "uvicorn", "plotly")  # the web extra (pyproject.toml)


def require_web() -> None:
    """The web extra is optional: without it, one line naming the command that installs it."""
    from importlib.util import find_spec

    missing = [name for name in WEB_MODULES if find_spec(name) is None]
    if missing:
        raise UsageError(f"serve: {', '.join(missing)} not installed; expected the web extra: "
                         f"pip install 'cuboid-fit[web]'")
