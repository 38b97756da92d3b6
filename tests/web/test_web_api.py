"""The web app's API as a hostile or careless client meets it: `stereo-bench serve` started as a
user starts it (tests/web_server.py), requests over HTTP on loopback. No browser needed."""

from __future__ import annotations

import copy
import http.client
import json
import time

import pytest

from web_server import call, running_server

BOMB = "\n".join(["a0: &a0 [x, x, x, x, x, x, x, x, x]"] + [
    f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * 9) + "]" for i in range(1, 10)])


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    runs = tmp_path_factory.mktemp("webapi") / "runs"
    with running_server(runs) as (url, _):
        status, example = call(url + "/api/example")
        assert status == 200
        yield url, runs, example


def _wait(url, job_id, states=("queued", "running"), seconds=120):
    deadline = time.monotonic() + seconds
    while True:
        status, job = call(f"{url}/api/jobs/{job_id}")
        if job["state"] not in states or time.monotonic() > deadline:
            return job
        time.sleep(0.1)


def test_requests_cannot_write_or_read_outside_the_runs_folder(server, tmp_path):
    url, runs, example = server
    for name in ("../escape", "/tmp/x", "a/b", ""):
        status, answer = call(url + "/api/runs", {"name": name, "config": example})
        assert status == 422 and "name" in answer["errors"][0]
    assert not (runs.parent / "escape").exists()
    for path in ("/runs/..%2F..%2Fetc/passwd", "/runs/x/..%2F..%2F..%2Fetc%2Fpasswd",
                 "/runs/x/a%00b", "/runs/%00/x"):
        status, _ = call(url + path)
        assert status == 404, path
    # A run folder that is a symlink to elsewhere serves nothing from there, is not listed, and
    # deleting it removes the link, not what it points to.
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "secret.txt").write_text("not yours")
    (elsewhere / "report.html").write_text("<p>not yours</p>")
    (runs / "linkrun").symlink_to(elsewhere)
    assert call(url + "/runs/linkrun/secret.txt")[0] == 404
    assert "linkrun" not in [r["name"] for r in call(url + "/api/runs")[1]]
    assert call(url + "/api/runs/linkrun", method="DELETE")[0] == 200
    assert (elsewhere / "secret.txt").read_text() == "not yours"
    status, answer = call(url + "/api/validate", {"config": {**example, "seed": -1}})
    assert status == 200 and not answer["ok"] and any("seed" in e for e in answer["errors"])


def test_another_host_name_is_refused(server):
    """DNS rebinding: a page of evil.example resolved to 127.0.0.1 sends Host: evil.example."""
    url, _, _ = server
    assert call(url + "/api/example", headers={"Host": "evil.example"})[0] == 400
    assert call(url + "/api/example", headers={"Host": "localhost:1"})[0] == 200


def test_bodies_are_bounded(server):
    url, _, _ = server
    # The body is refused unread, so the server may answer and close before a client has sent
    # it all (a broken pipe for the client): announce 3 MiB and send none of it.
    host, port = url.removeprefix("http://").split(":")
    connection = http.client.HTTPConnection(host, int(port), timeout=30)
    connection.putrequest("POST", "/api/validate")
    connection.putheader("Content-Type", "application/json")
    connection.putheader("Content-Length", str(3 << 20))
    connection.endheaders()
    response = connection.getresponse()
    status, answer = response.status, json.loads(response.read())
    connection.close()
    assert status == 413 and "request body" in answer["errors"][0]
    deep = b'{"config": ' + b"[" * 100_000 + b"]" * 100_000 + b"}"
    status, answer = call(url + "/api/validate", raw=deep)
    assert status in (400, 422) and answer["ok"] is False


def test_an_alias_bomb_is_refused_at_once(server):
    url, _, example = server
    start = time.perf_counter()
    status, answer = call(url + "/api/yaml", {"text": BOMB}, timeout=10)
    assert status == 200 and not answer["ok"] and "aliases" in answer["errors"][0]
    status, answer = call(url + "/api/sweeps", {"name": "bomb", "config": example,
                                                "axes": BOMB, "trials": 1}, timeout=10)
    assert status == 422 and "aliases" in answer["errors"][0]
    assert time.perf_counter() - start < 5


def test_a_sweep_with_a_bad_axis_is_refused_before_it_is_a_job(server):
    url, runs, example = server
    status, answer = call(url + "/api/sweeps", {"name": "badaxis", "config": example,
                                                "axes": "environment.nope: [1, 2]", "trials": 1})
    assert status == 422 and "axes.environment.nope" in answer["errors"][0]
    assert not (runs / "badaxis").exists()
    assert all(j["name"] != "badaxis" for j in call(url + "/api/jobs")[1])


def test_requests_over_the_budget_are_refused_with_their_cost(server):
    url, runs, example = server
    big = copy.deepcopy(example)
    for cam in big["cameras"]:
        cam.update(width=8000, height=8000, fx=6000.0, fy=6000.0, cx=4000.0, cy=4000.0)
    big["environment"]["supersampling"] = 16
    start = time.perf_counter()
    status, answer = call(url + "/api/preview", {"config": big, "camera": 0, "frame": 0})
    assert status == 422 and "16,384,000,000 samples" in answer["errors"][0]
    long = copy.deepcopy(example)
    long["trajectory"]["frames"] = 10_000
    for cam in long["cameras"]:
        cam.update(width=4000, height=3000, fx=3000.0, fy=3000.0, cx=2000.0, cy=1500.0)
    status, answer = call(url + "/api/runs", {"name": "long", "config": long})
    assert status == 422 and "960,000,000,000 samples" in answer["errors"][0]
    assert time.perf_counter() - start < 5
    assert not (runs / "long").exists()


def test_a_running_job_is_cancelled_within_seconds_and_its_folder_deleted(server):
    url, runs, example = server
    rig = copy.deepcopy(example)
    rig["trajectory"]["frames"] = 400  # minutes of work: it must be stopped, not finished
    status, job = call(url + "/api/runs", {"name": "stopme", "config": rig})
    assert status == 200
    job = _wait(url, job["id"], states=("queued",))
    deadline = time.monotonic() + 60
    while call(f"{url}/api/jobs/{job['id']}")[1]["done"] == 0 and time.monotonic() < deadline:
        time.sleep(0.1)
    # While it writes, its folder cannot be deleted.
    status, answer = call(url + "/api/runs/stopme", method="DELETE")
    assert status == 409 and "cancel it first" in answer["errors"][0]
    start = time.monotonic()
    assert call(f"{url}/api/jobs/{job['id']}/cancel", method="POST")[0] == 200
    job = _wait(url, job["id"])
    stopped = time.monotonic() - start
    print(f"cancelled job stopped in {stopped:.2f} s at {job['stage']} {job['done']}/"
          f"{job['total']}")
    assert job["state"] == "cancelled" and stopped < 5
    # Its lock went with it: a new run into the same folder starts (and is cancelled too).
    status, again = call(url + "/api/runs", {"name": "stopme", "config": rig})
    assert status == 200
    call(f"{url}/api/jobs/{again['id']}/cancel", method="POST")
    assert _wait(url, again["id"])["state"] == "cancelled"
    assert call(url + "/api/runs/stopme", method="DELETE")[0] == 200
    assert not (runs / "stopme").exists()
    assert call(url + "/api/runs/stopme", method="DELETE")[0] == 404
    assert call(url + "/api/jobs/999/cancel", method="POST")[0] == 404


def test_a_preview_answers_and_says_what_it_shows(server):
    url, _, example = server
    status, png = call(url + "/api/preview", {"config": example, "camera": 1, "frame": 3})
    assert status == 200 and png[:8] == b"\x89PNG\r\n\x1a\n"
    status, answer = call(url + "/api/preview", {"config": example, "camera": 5, "frame": 0})
    assert status == 422 and "camera 0..1" in answer["errors"][0]
    assert json.dumps(answer)  # an answer in words, not a server error
