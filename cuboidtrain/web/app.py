"""The page's web app (Starlette): the page, its scripts, and three ways to ask for a fit.

    GET  /                        the page (static/index.html); /static/*: its own script and style
    GET  /vendor/plotly.min.js    the 3D view's library, from the pinned `plotly` package: no CDN
    GET  /api/info                the options' choices and defaults, the upload limit, the examples
    POST /api/fit?name=N&...      the request's body is a mask file's bytes
    POST /api/example/NAME?...    a shipped example (examples/)
    POST /api/generated?...       a mask drawn by the generator, fitted with its truth beside it

`explain=0` leaves the explanation panel out of the answer (the page asks for it in a second
request: it takes 10-30 times the fit to draw). The options are query parameters named as `infer`'s (`shape`, `invert`, `threshold`,
`label_id`, `no_classifier`, `focal_px`, `principal_x`, `principal_y`), read into `FitOptions` with
`cuboid=True`, as `infer` has them. A bad option or an upload over the limit is a 400 or 413
whose JSON `error` is one line; an input that cannot be fitted is a record with its `error`,
as `infer` writes it. The answer is made in a worker (`server.FitPool`; `answer.fit_upload`).
"""
from __future__ import annotations

import logging
import math
from contextlib import asynccontextmanager
from functools import lru_cache
from importlib import resources
from pathlib import Path

from starlette.applications import Starlette
from starlette.requests import Request
from starlette.responses import FileResponse, JSONResponse, Response
from starlette.routing import Mount, Route
from starlette.staticfiles import StaticFiles

from cuboidtrain.experiments.generated_mask import GENERATED_SHAPES, MASK_SIZES
from cuboidtrain.fit.options import FIT_SHAPES, FitOptions
from cuboidtrain.web.answer import PageRequest, fit_generated, fit_upload
from shared.errors import UsageError

log = logging.getLogger(__name__)
STATIC = Path(__file__).parent / "static"
EXAMPLES = Path(__file__).resolve().parents[2] / "examples"  # a checkout's (an editable install's) examples/
SCENES = ("paper", "paper-clean", "street", "irregular")  # cuboidgen's scenes (cuboidgen.config.SCENES)
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")


def make_app(config, pool) -> Starlette:
    """The app for a `server.ServeConfig`; `pool` (a `server.FitPool`) warms up as it starts and stops with it."""

    @asynccontextmanager
    async def lifespan(app):
        app.state.pool = pool
        await app.state.pool.warm_up()
        try:
            yield
        finally:
            app.state.pool.close()

    async def info(request: Request) -> Response:
        defaults = FitOptions()
        return JSONResponse({"shapes": list(FIT_SHAPES), "shape": defaults.shape, "max_upload_bytes": config.max_upload_bytes,
                             "examples": examples(), "generated_shapes": list(GENERATED_SHAPES), "scenes": list(SCENES),
                             "sizes": list(MASK_SIZES), "workers": config.workers})

    async def fit(request: Request) -> Response:
        try:
            options = page_options(request.query_params)
            data = await read_upload(request, config.max_upload_bytes)
        except UsageError as error:
            return refused(error, 413 if "limit" in str(error) else 400)
        name = request.query_params.get("name") or "mask.png"
        return await answered(request, fit_upload, PageRequest(data, name, options, flag(request.query_params, "explain", True)))

    async def example(request: Request) -> Response:
        name = request.path_params["name"]
        try:
            if name not in examples():
                raise UsageError(f"example {name!r}: expected one of {', '.join(examples()) or 'none (no examples/ here)'}")
            options = page_options(request.query_params)
        except UsageError as error:
            return refused(error, 400)
        data = (EXAMPLES / name).read_bytes()
        return await answered(request, fit_upload, PageRequest(data, name, options, flag(request.query_params, "explain", True)))

    async def generated(request: Request) -> Response:
        query = request.query_params
        try:
            options = page_options(query)
            seed = whole(query, "seed", 0)
            size = whole(query, "size", 256)
        except UsageError as error:
            return refused(error, 400)
        return await answered(request, fit_generated, query.get("gen_shape", "mix"), query.get("scene", "paper"),
                              size, seed, options, flag(query, "explain", True))

    routes = [Route("/", lambda request: FileResponse(STATIC / "index.html")),
              Route("/favicon.ico", lambda request: Response(status_code=204)),
              Route("/vendor/plotly.min.js", lambda request: FileResponse(plotly_js(), media_type="text/javascript")),
              Route("/api/info", info), Route("/api/fit", fit, methods=["POST"]),
              Route("/api/example/{name}", example, methods=["POST"]),
              Route("/api/generated", generated, methods=["POST"]),
              Mount("/static", StaticFiles(directory=STATIC), name="static")]
    return Starlette(routes=routes, lifespan=lifespan)


async def answered(request: Request, fn, *args) -> Response:
    """`fn(*args)`'s answer from a worker, as JSON; a UsageError raised there (a bad generated
    shape, scene or size; a worker that died) is a 400 with its line, anything else a 500 with
    one line, and the server goes on."""
    try:
        return JSONResponse(await request.app.state.pool.run(fn, *args))
    except UsageError as error:
        return refused(error, 400)
    except Exception as error:  # a bug: said in one line, logged in full; the next request is served
        log.exception("%s failed", request.url.path)
        return refused(RuntimeError(f"the page failed on this input ({type(error).__name__}: {error})"), 500)


def refused(error: Exception, status: int) -> JSONResponse:
    return JSONResponse({"error": " ".join(str(error).split())}, status_code=status)


@lru_cache(maxsize=1)
def plotly_js() -> Path:
    """plotly.js as the installed `plotly` package ships it (the version constraints.txt pins)."""
    path = Path(str(resources.files("plotly") / "package_data" / "plotly.min.js"))
    if not path.is_file():
        raise FileNotFoundError(f"{path}: the plotly package has no plotly.min.js; expected plotly's wheel")
    return path


def examples() -> list[str]:
    """The shipped example masks (examples/ beside the package, in a checkout), by file name."""
    if not EXAMPLES.is_dir():
        return []
    return sorted(p.name for p in EXAMPLES.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())


async def read_upload(request: Request, limit: int) -> bytes:
    """The request's body, refused (a one-line UsageError) once it is over `limit` bytes, before
    more is read: by its Content-Length when it says, else as it streams in."""
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > limit:
        raise UsageError(over_limit(int(declared), limit))
    chunks, size = [], 0
    async for chunk in request.stream():
        size += len(chunk)
        if size > limit:
            raise UsageError(over_limit(size, limit, at_least=True))
        chunks.append(chunk)
    return b"".join(chunks)


def over_limit(size: int, limit: int, at_least: bool = False) -> str:
    return (f"upload of {'over ' if at_least else ''}{size / 1e6:.1f} MB: over the page's limit of {limit / 1e6:g} MB; "
            f"expected a smaller file (cuboidtrain serve --max-upload-mb raises it; cuboidtrain infer has none)")


def page_options(query) -> FitOptions:
    """The page's options as `infer` reads them (cuboid fit on), checked: a one-line UsageError
    naming the option and what it takes."""
    principal = (optional_number(query, "principal_x"), optional_number(query, "principal_y"))
    if (principal[0] is None) != (principal[1] is None):
        raise UsageError(f"--principal-px {principal}: expected both X and Y, or neither")
    options = FitOptions(shape=query.get("shape", "auto"), invert=flag(query, "invert"),
                         threshold=optional_number(query, "threshold"), label_id=optional_whole(query, "label_id"),
                         cuboid=True, shape_classifier=not flag(query, "no_classifier"), device="cpu",
                         focal_px=optional_number(query, "focal_px"),
                         principal_px=None if principal[0] is None else principal)
    return options.validate()


def flag(query, name: str, default: bool = False) -> bool:
    value = query.get(name, "1" if default else "0").lower()
    if value not in ("0", "1", "true", "false", "on", "off", ""):
        raise UsageError(f"--{name.replace('_', '-')} {value!r}: expected on or off")
    return value in ("1", "true", "on")


def optional_number(query, name: str) -> float | None:
    text = query.get(name, "").strip()
    if not text:
        return None
    try:
        value = float(text)
    except ValueError:
        raise UsageError(f"--{name.replace('_', '-')} {text!r}: expected a number") from None
    if not math.isfinite(value):
        raise UsageError(f"--{name.replace('_', '-')} {text!r}: expected a finite number")
    return value


def optional_whole(query, name: str) -> int | None:
    value = optional_number(query, name)
    if value is not None and not value.is_integer():
        raise UsageError(f"--{name.replace('_', '-')} {value:g}: expected a whole number")
    return None if value is None else int(value)


def whole(query, name: str, default: int) -> int:
    value = optional_whole(query, name)
    return default if value is None else value
