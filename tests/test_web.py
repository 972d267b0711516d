"""The page's server (`cuboidtrain serve`, issue 41): infer's answer over HTTP, its errors in one line,
the upload limit, two users at once, generated masks with their truth, a clean stop on Ctrl-C."""
from __future__ import annotations

import http.client
import json
import signal
import urllib.error
import urllib.request
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from urllib.parse import urlparse

import cv2
import pytest
from typer.testing import CliRunner

from cuboidtrain.cli import app
from tests.test_not_a_mask import building, photo

ROOT = Path(__file__).resolve().parents[1]


def post(url: str, data: bytes = b"") -> tuple[int, dict]:
    try:
        with urllib.request.urlopen(urllib.request.Request(url, data=data, method="POST"), timeout=120) as response:
            return response.status, json.loads(response.read())
    except urllib.error.HTTPError as error:
        return error.code, json.loads(error.read())


def announce_upload(address: str, size: int) -> tuple[int, dict]:
    """A POST that says its size and waits for the answer before sending a byte: refused by its size."""
    parts = urlparse(address)
    connection = http.client.HTTPConnection(parts.hostname, parts.port, timeout=60)
    try:
        connection.putrequest("POST", "/api/fit?name=big.png")
        connection.putheader("Content-Length", str(size))
        connection.endheaders()
        response = connection.getresponse()
        return response.status, json.loads(response.read())
    finally:
        connection.close()


def infer(path: Path, *options: str) -> dict:
    result = CliRunner().invoke(app, ["infer", str(path), "--device", "cpu", "--json", "-", *options])
    [record] = json.loads(result.stdout)
    return record


def test_the_page_answers_with_infers_record_mesh_and_view(page_server):
    address, _ = page_server
    status, answer = post(f"{address}api/fit?name=building.png&explain=0", (ROOT / "examples/building.png").read_bytes())
    assert status == 200 and answer["panel"] is None
    assert answer["record"] == infer(ROOT / "examples/building.png") | {"input": "building.png"}
    assert answer["mesh"].startswith("# cuboidtrain infer --cuboid --mesh: box fitted to building.png\n")
    box = answer["view"]["box3d"]
    assert len(box["corners"]) == 8 and len(box["faces"]) == 6 and box["band"]["factor"] > 1
    assert (answer["view"]["width"], answer["view"]["height"]) == (420, 360)


def test_the_options_are_infers_and_the_panel_comes_when_asked(page_server, tmp_path):
    address, _ = page_server
    mask = tmp_path / "dark.png"
    cv2.imwrite(str(mask), (~building()).astype("uint8") * 255)  # a dark building on white: --invert
    query = "name=dark.png&shape=twobox&invert=1&focal_px=300&principal_x=80&principal_y=60"
    status, answer = post(f"{address}api/fit?{query}", mask.read_bytes())
    assert status == 200 and answer["panel"]  # explain defaults on: the PNG, base64
    expected = infer(mask, "--shape", "twobox", "--invert", "--focal-px", "300", "--principal-px", "80", "60")
    assert answer["record"] == expected | {"input": "dark.png"}
    assert answer["record"]["cuboid"]["intrinsics"] == {"focal_px": "given", "principal_px": "given"}
    status, answer = post(f"{address}api/fit?name=dark.png&invert=1&no_classifier=1", mask.read_bytes())
    assert status == 200 and answer["record"] == infer(mask, "--invert", "--no-classifier") | {"input": "dark.png"}
    assert answer["record"]["shape_call"] is None  # the silhouettes alone chose


def test_bad_input_is_infers_one_line_error_and_the_server_goes_on(page_server, tmp_path):
    address, server = page_server
    cv2.imwrite(str(tmp_path / "photo.jpg"), photo())
    status, answer = post(f"{address}api/fit?name=photo.jpg", (tmp_path / "photo.jpg").read_bytes())
    expected = infer(tmp_path / "photo.jpg")["error"].replace(f"{tmp_path}/", "")
    assert status == 200 and answer["record"]["error"] == expected and "not a binary mask" in expected
    assert post(f"{address}api/fit?name=empty.png")[1]["record"]["error"].startswith("empty.png: cannot read image")
    status, answer = announce_upload(address, 2_000_001)  # the fixture's limit: 2 MB
    assert status == 413 and answer["error"].startswith("upload of 2.0 MB: over the page's limit of 2 MB")
    status, answer = post(f"{address}api/fit?threshold=high", b"x")
    assert (status, answer) == (400, {"error": "--threshold 'high': expected a number"})
    status, answer = post(f"{address}api/fit?label_id=3&invert=1", b"x")
    assert status == 400 and answer["error"].startswith("--invert with --label-id 3: expected one of them")
    status, answer = post(f"{address}api/example/nothing.png")
    assert status == 400 and "expected one of building.png" in answer["error"]
    assert server.poll() is None and post(f"{address}api/example/building.png?explain=0")[0] == 200


def test_two_users_at_once_each_get_their_own_answer(page_server):
    address, _ = page_server
    with ThreadPoolExecutor(2) as users:
        box = users.submit(post, f"{address}api/example/building.png?explain=0&shape=box")
        twobox = users.submit(post, f"{address}api/example/building.png?explain=0&shape=twobox")
        assert box.result()[1]["record"]["shape"] == "box" and twobox.result()[1]["record"]["shape"] == "twobox"


def test_a_generated_mask_comes_with_its_truth_and_the_errors(page_server):
    address, _ = page_server
    status, answer = post(f"{address}api/generated?gen_shape=box&scene=paper-clean&size=128&seed=4&explain=0")
    assert status == 200 and answer["truth"]["shape"] == "box" and len(answer["truth"]["keypoints"]) == 8
    assert answer["record"]["shape"] == "box" and 0 <= answer["errors"]["mean_corner_px"] < 20
    assert set(answer["truth"]["camera"]) == {"focal_px", "principal_px"}
    status, answer = post(f"{address}api/generated?scene=moon")
    assert status == 400 and answer["error"] == "scene 'moon': expected one of paper, paper-clean, street, irregular"


@pytest.mark.stops_page_server  # the session's server, after every other test that uses it
def test_ctrl_c_stops_the_server_cleanly(page_server):
    _, server = page_server
    assert server.poll() is None  # it served every page test before this one
    server.send_signal(signal.SIGINT)
    assert server.wait(30) == 0
    said = server.stderr.read()
    assert "stopped" in said and "Traceback" not in said


def test_the_server_refuses_an_address_that_is_not_one():
    result = CliRunner().invoke(app, ["serve", "--host", "example.com"])
    assert result.exit_code != 0 and "--host 'example.com': expected an IP address" in result.output


def test_the_server_says_its_address_only_once_it_listens():
    # uvicorn runs the app's lifespan (the workers' warm-up) before it binds the socket: an address
    # said from the lifespan was refused to whoever used it at once (a page test met exactly that).
    import asyncio
    import socket
    import threading

    uvicorn = pytest.importorskip("uvicorn")
    from cuboidtrain.web.server import ServeConfig, announcing_server

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]

    async def slow_to_start(scope, receive, send):  # an app whose start-up takes a while, as the pool's does
        assert scope["type"] == "lifespan"
        while True:
            message = await receive()
            if message["type"] == "lifespan.startup":
                await asyncio.sleep(0.3)
                await send({"type": "lifespan.startup.complete"})
            else:
                await send({"type": "lifespan.shutdown.complete"})
                return

    heard = []

    def announce():
        with socket.create_connection(("127.0.0.1", port), timeout=5):  # refused if said too early
            heard.append("listening")
        server.should_exit = True

    server = announcing_server(uvicorn, slow_to_start, ServeConfig(port=port), announce)
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    thread.join(60)
    assert heard == ["listening"] and not thread.is_alive()
