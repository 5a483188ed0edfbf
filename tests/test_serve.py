"""The HTTP service on a hand-made store with the fake adapters: answers, errors, limits, token, reload."""

from __future__ import annotations

import base64
import io
import threading
import time
import zipfile
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from query_helpers import fake_models, make_fake_store, object_image
from serve_helpers import add_fake_mesh

pytest.importorskip("fastapi", reason="fastapi not installed (the serve dependencies)")
pytest.importorskip("httpx", reason="httpx not installed (FastAPI's TestClient needs it)")

from fastapi.testclient import TestClient  # noqa: E402

from pipeline.query import Retriever  # noqa: E402
from pipeline.serve.app import create_app  # noqa: E402
from pipeline.serve.service import QueryService, ServiceLimits  # noqa: E402


def png(img) -> bytes:
    buf = io.BytesIO()
    img.save(buf, format="PNG")
    return buf.getvalue()


def red_can():
    img = object_image("red", 44, 52, pad=30)
    mask = np.abs(np.asarray(img, np.int16) - 205).sum(axis=2) > 30
    ys, xs = np.nonzero(mask)
    return img, mask, f"{xs.min()},{ys.min()},{xs.max() + 1},{ys.max() + 1}"


def make_service(store, **limits) -> QueryService:
    r = Retriever.open(store, models=fake_models(), use_cache=False)
    return QueryService(r, ServiceLimits(**{"reload_interval": 0, "workers": 2, **limits}))


@pytest.fixture()
def store(tmp_path):
    return make_fake_store(tmp_path / "store")


@pytest.fixture()
def client(store):
    service = make_service(store)
    with TestClient(create_app(service)) as c:
        yield c
    service.close()


def post_query(client, img, prompt="the red can", headers=None, **form):
    files = {"image": ("photo.png", png(img), "image/png")}
    return client.post("/query", files=files, data={"prompt": prompt, **form}, headers=headers or {})


def test_query_answers_like_the_python_api(client, store):
    img, mask, box = red_can()
    r = post_query(client, img, box=box, roi="bbox", top=3)
    assert r.status_code == 200, r.text
    got = r.json()
    with Retriever.open(store, models=fake_models(), use_cache=False) as ret:
        want = ret.query(img, "the red can", box=box, roi_mode="bbox", top=3).to_dict()
    want["query"]["image"] = "photo.png"
    got.pop("timings_ms"), want.pop("timings_ms")
    assert got == want
    assert got["candidates"][0]["name"] == "red_can"


def test_query_with_mask_and_batch(client):
    img, mask, box = red_can()
    from PIL import Image

    mask_png = png(Image.fromarray(mask.astype(np.uint8) * 255))
    files = {"image": ("p.png", png(img), "image/png"), "mask": ("m.png", mask_png, "image/png")}
    r = client.post("/query", files=files, data={"prompt": "the red can"})
    assert r.status_code == 200, r.text
    assert r.json()["query"]["roi"]["source"] == "mask"
    b64 = base64.b64encode(png(img)).decode()
    yellow = base64.b64encode(png(object_image("yellow", 30, 72, pad=30))).decode()
    body = {
        "queries": [
            {"id": "a", "image_b64": b64, "prompt": "the red can", "box": box},
            {"image_b64": yellow, "prompt": "the yellow bottle", "box": [30, 30, 60, 102]},
            {"id": "bad", "image_b64": "!!notbase64", "prompt": "x"},
        ],
        "top": 2,
        "roi": "bbox",
    }
    r = client.post("/query/batch", json=body)
    assert r.status_code == 200, r.text
    res = r.json()["results"]
    assert res[0]["id"] == "a" and res[0]["candidates"][0]["name"] == "red_can"
    assert res[1]["id"] == 2 and res[1]["candidates"][0]["name"] == "yellow_bottle"
    assert res[2] == {"id": "bad", "error": "image_b64 is not valid base64"}


def test_meshes_views_export_health_stats(client, store, tmp_path):
    lib = tmp_path / "lib"
    (lib / "purple" / "tex").mkdir(parents=True)
    (lib / "purple" / "model.obj").write_text("mtllib model.mtl\nv 0 0 0\n")
    (lib / "purple" / "model.mtl").write_text("newmtl m\nmap_Kd tex/t.png\n")
    (lib / "purple" / "tex" / "t.png").write_bytes(b"png")
    mid = add_fake_mesh(
        store, "purple", (120, 40, 160), 40, 60, library_root=str(lib), deps=["model.mtl", "tex/t.png"]
    )
    client.app.state.service.reload_if_changed()
    m = client.get(f"/meshes/{mid}")
    assert m.status_code == 200, m.text
    rec = m.json()
    assert rec["name"] == "purple" and [v["view_index"] for v in rec["views"]] == [0, 1]
    v = client.get(rec["views"][1]["url"])
    assert v.status_code == 200 and v.headers["content-type"] == "image/png" and v.content[:4] == b"\x89PNG"
    assert rec["units_guess"] is None and rec["extent_m"] is None  # no geometry recorded: no size claimed
    z = client.get(f"/meshes/{mid}/export?units=source")
    assert z.status_code == 200 and z.headers["content-type"] == "application/zip"
    names = sorted(zipfile.ZipFile(io.BytesIO(z.content)).namelist())
    assert names == ["purple/model.mtl", "purple/model.obj", "purple/model_info.json", "purple/tex/t.png"]
    metres = client.get(f"/meshes/{mid}/export")  # metres by default: this mesh has no recorded units
    assert metres.status_code == 409 and "no recorded size or units" in metres.json()["error"]
    assert client.get(f"/meshes/{mid}/export?units=cm").status_code == 422
    assert client.get(f"/meshes/{mid}/export?units=source&view=9").status_code == 404
    assert client.get("/meshes/nope").status_code == 404
    assert client.get(f"/meshes/{mid}/views/7.png").status_code == 404
    h = client.get("/health").json()
    assert h["status"] == "ok" and h["meshes"] == 5
    s = client.get("/stats").json()
    assert s["meshes"] == 5 and s["reloads"] == 1 and s["store_version"] == h["store_version"]
    assert client.get("/openapi.json").json()["paths"].keys() >= {"/query", "/query/batch", "/stats"}
    assert client.get("/docs").status_code == 200
    page = client.get("/")
    assert page.status_code == 200 and 'id="results"' in page.text


BAD_REQUESTS = [
    ("no image", lambda c: c.post("/query", data={"prompt": "x"}), 422),
    ("no prompt", lambda c: c.post("/query", files={"image": ("a.png", b"x")}), 422),
    (
        "not an image",
        lambda c: c.post("/query", files={"image": ("a.png", b"hello")}, data={"prompt": "a can"}),
        422,
    ),
    (
        "empty image",
        lambda c: c.post("/query", files={"image": ("a.png", b"")}, data={"prompt": "a can"}),
        422,
    ),
    ("bad box", lambda c: post_query(c, red_can()[0], box="1,2,three"), 422),
    ("box outside", lambda c: post_query(c, red_can()[0], box="500,500,600,600"), 422),
    ("inverted box", lambda c: post_query(c, red_can()[0], box="50,50,10,10"), 422),
    ("no box, no detector", lambda c: post_query(c, red_can()[0]), 422),
    ("empty prompt", lambda c: post_query(c, red_can()[0], prompt="  ", box=red_can()[2]), 422),
    ("bad mode", lambda c: post_query(c, red_can()[0], box=red_can()[2], mode="magic"), 422),
    ("bad roi", lambda c: post_query(c, red_can()[0], box=red_can()[2], roi="x"), 422),
    ("top 0", lambda c: post_query(c, red_can()[0], box=red_can()[2], top=0), 422),
    ("top text", lambda c: post_query(c, red_can()[0], box=red_can()[2], top="many"), 422),
    ("threshold text", lambda c: post_query(c, red_can()[0], box=red_can()[2], threshold="hi"), 422),
    (
        "mask of another size",
        lambda c: c.post(
            "/query",
            files={"image": ("a.png", png(red_can()[0])), "mask": ("m.png", png(object_image("red", 5, 5)))},
            data={"prompt": "a can"},
        ),
        422,
    ),
    (
        "batch not json",
        lambda c: c.post("/query/batch", content=b"{", headers={"content-type": "application/json"}),
        422,
    ),
    ("batch wrong shape", lambda c: c.post("/query/batch", json={"queries": "x"}), 422),
    (
        "batch too many",
        lambda c: c.post("/query/batch", json={"queries": [{"image_b64": "", "prompt": "x"}] * 40}),
        413,
    ),
    ("unknown route", lambda c: c.get("/nope"), 404),
    ("wrong method", lambda c: c.get("/query"), 405),
    ("view index text", lambda c: c.get("/meshes/x/views/abc.png"), 422),
    (
        "too large",
        lambda c: c.post("/query", content=b"x" * (3 << 20), headers={"content-type": "image/png"}),
        413,
    ),
    (
        "too large, chunked",
        lambda c: c.post(
            "/query",
            content=iter([b"x" * (1 << 20)] * 3),
            headers={"content-type": "multipart/form-data; boundary=b"},
        ),
        413,
    ),
    (
        "too many pixels",
        lambda c: post_query(c, object_image("red", 2000, 1100, pad=0), box="1,1,50,50"),
        413,
    ),
]


@pytest.mark.parametrize("name,call,status", BAD_REQUESTS, ids=[b[0] for b in BAD_REQUESTS])
def test_bad_requests_get_a_json_4xx(store, name, call, status):
    service = make_service(store, max_body_bytes=2 << 20, max_pixels=2_000_000, max_batch=32)
    with TestClient(create_app(service), raise_server_exceptions=False) as c:
        r = call(c)
    service.close()
    assert r.status_code == status, (name, r.status_code, r.text)
    body = r.json()
    assert isinstance(body.get("error"), str) and body["error"] and "Traceback" not in r.text


def test_token_is_required_when_set(store):
    service = make_service(store)
    img, _, box = red_can()
    with TestClient(create_app(service, token="s3cret")) as c:
        assert c.get("/health").status_code == 200  # liveness stays open
        assert c.get("/").status_code == 200
        r = post_query(c, img, box=box)
        assert (
            r.status_code == 401
            and r.headers["www-authenticate"] == "Bearer"
            and "token" in r.json()["error"]
        )
        assert c.get("/stats", headers={"Authorization": "Bearer wrong"}).status_code == 401
        ok = post_query(c, img, box=box, headers={"Authorization": "Bearer s3cret"})
        assert ok.status_code == 200
    service.close()


def test_concurrent_clients_and_busy_limit(store):
    service = make_service(store, workers=2, max_pending=64)
    img, _, box = red_can()
    with TestClient(create_app(service)) as c:
        with ThreadPoolExecutor(max_workers=8) as pool:
            codes = list(pool.map(lambda _: post_query(c, img, box=box).status_code, range(32)))
        assert codes == [200] * 32
        assert c.get("/stats").json()["queries"] == 32
    service.close()
    tiny = make_service(store, workers=1, max_pending=1)
    gate = threading.Event()
    tiny.pool.submit(gate.wait)  # occupy the only worker
    with TestClient(create_app(tiny)) as c:
        with ThreadPoolExecutor(max_workers=4) as pool:
            futures = [pool.submit(post_query, c, img, box=box) for _ in range(4)]
            time.sleep(0.5)
            gate.set()
            codes = sorted(f.result().status_code for f in futures)
    tiny.close()
    assert 503 in codes and 200 in codes, codes


def test_mesh_committed_while_serving_is_returned(store):
    service = make_service(store, reload_interval=0.2)
    service.start_polling()
    img = object_image("yellow", 30, 72, pad=30)
    with TestClient(create_app(service)) as c:
        before = post_query(c, img, prompt="the yellow bottle", box="30,30,60,102", roi="bbox", top=10).json()
        assert "yellow_twin" not in [x["name"] for x in before["candidates"]]
        add_fake_mesh(store, "yellow_twin", (230, 200, 40), 30, 70)
        t0 = time.monotonic()
        while time.monotonic() - t0 < 10:
            r = post_query(c, img, prompt="the yellow bottle", box="30,30,60,102", roi="bbox", top=10).json()
            if "yellow_twin" in [x["name"] for x in r["candidates"]]:
                break
            time.sleep(0.1)
        else:
            pytest.fail("the new mesh was not returned within 10 s")
        assert c.get("/stats").json()["reloads"] == 1
    service.close()


def test_inflight_query_finishes_on_the_old_snapshot(store):
    service = make_service(store)
    old = service.acquire()  # an in-flight request
    add_fake_mesh(store, "late", (10, 200, 10), 40, 40)
    assert service.reload_if_changed()
    assert service.snapshot is not old and service.snapshot.retriever.n_meshes == 5
    img, _, box = red_can()
    assert old.retriever.query(img, "the red can", box=box, roi_mode="bbox").best.name == "red_can"
    assert old.retriever.text_filter._all  # still open while in use
    old.release()  # the last user closes the retired snapshot
    assert old.retriever.text_filter._all == []
    service.close()
