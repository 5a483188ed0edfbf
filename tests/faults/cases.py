"""The fault corpus: each case is generated in code (no binary fixtures) against a copy of a small store.

``CASES`` lists every case; ``tests/test_fault_corpus.py`` runs them. Add a case by appending to the
list a :class:`~faults.harness.Case` whose ``act`` does one hostile or unlucky thing.
"""

from __future__ import annotations

import errno
import os
import socket
import struct
import zlib
from pathlib import Path

from faults.harness import Case, Env
from faults.library import write_textured_obj

CASES: list[Case] = []


def case(name: str, tool: str, outcome: str, expect: str = "", **kw):
    """Decorator: register ``act`` as a case."""

    def wrap(act):
        CASES.append(Case(name, tool, outcome, act, expect, **kw))
        return act

    return wrap


def option_error(tool: str, name: str, argv, expect: str) -> None:
    """A command-line value that must be refused when parsed."""

    def act(env: Env):
        if tool == "onboard":
            return env.onboard(*argv)
        if tool == "sql":
            return env.sql(*argv)
        if tool == "query":
            return env.cli("query", ["--store", env.store, *argv])
        if tool == "evaluate":
            return env.cli("evaluate", ["--store", env.store, "--out", env.tmp / "rep", *argv])
        return env.cli(tool, argv)

    CASES.append(Case(name, tool, "error", act, expect))


# ================================================================== onboard: options
for _name, _argv, _expect in [
    ("resolution_zero", ["--resolution", "0"], ">= 16"),
    ("resolution_huge", ["--resolution", "100000"], "<= 8192"),
    ("resolution_text", ["--resolution", "big"], "integer"),
    ("upper_ring_nan", ["--upper-ring-offset", "nan"], "finite"),
    ("elevations_out_of_range", ["--elevations=-15,95"], "<= 89"),
    ("elevations_text", ["--elevations", "low,high"], "a number"),
    ("elevations_too_many", ["--elevations", "0,10,20,30,40,50,60"], "1 to 6 elevation rings"),
    ("upper_ring_inf", ["--upper-ring-offset=-inf"], "finite"),
    ("render_timeout_negative", ["--render-timeout", "-5"], "> 0"),
    ("render_timeout_zero", ["--render-timeout", "0"], "> 0"),
    ("render_timeout_nan", ["--render-timeout", "nan"], "finite"),
    ("workers_negative", ["--workers", "-1"], ">= 0"),
    ("batch_size_zero", ["--batch-size", "0"], ">= 1"),
    ("max_faces_zero", ["--max-faces", "0"], ">= 1"),
    ("max_texture_pixels_negative", ["--max-texture-pixels", "-1"], ">= 1"),
    ("ray_gpus_nan", ["--ray-gpus-per-actor", "nan"], "finite"),
    ("ray_actors_zero", ["--ray-embed-actors", "0"], ">= 1"),
    ("unknown_prompt_style", ["--prompt-style", "poetic"], "invalid choice"),
    ("unknown_model_role", ["--model", "painter=x"], "unknown model role"),
]:
    option_error("onboard", f"onboard_{_name}", _argv, _expect)


@case("onboard_library_missing", "onboard", "error", "library folder not found")
def _(env: Env):
    return env.onboard(library=env.tmp / "nowhere")


@case("onboard_library_is_a_file", "onboard", "error", "is a file: give the folder that holds the meshes")
def _(env: Env):
    (env.tmp / "lib.txt").write_text("x")
    return env.onboard(library=env.tmp / "lib.txt")


@case("onboard_store_is_a_file", "onboard", "error", "is a file")
def _(env: Env):
    (env.tmp / "store.txt").write_text("x")
    return env.onboard(store=env.tmp / "store.txt")


@case("onboard_store_not_a_store", "onboard", "error", "not an OSCAR store")
def _(env: Env):
    (env.tmp / "docs").mkdir()
    (env.tmp / "docs" / "a.txt").write_text("x")
    return env.onboard(store=env.tmp / "docs")


@case("onboard_store_locked", "onboard", "error", "locked by another writer")
def _(env: Env):
    from pipeline.store import Store

    with Store.open(env.store, writable=True):
        return env.onboard()


def _fail_os_open(env: Env, name: str, err: int) -> None:
    """Make ``os.open`` of store files named ``name`` fail with ``err`` (a read-only or full disk)."""
    import pipeline.store as store_mod

    real = os.open

    def fake(path, flags, *a, **k):
        if Path(path).name == name and (flags & (os.O_WRONLY | os.O_RDWR | os.O_CREAT)):
            raise OSError(err, os.strerror(err), str(path))
        return real(path, flags, *a, **k)

    env.monkeypatch.setattr(store_mod.os, "open", fake)


@case("onboard_store_read_only_lock", "onboard", "error", "read-only file system")
def _(env: Env):
    _fail_os_open(env, "_lock", errno.EROFS)
    return env.onboard()


@case("onboard_store_lock_permission", "onboard", "error", "permission denied")
def _(env: Env):
    _fail_os_open(env, "_lock", errno.EACCES)
    return env.onboard()


def _new_mesh(env: Env) -> None:
    write_textured_obj(env.lib / "new_cube", colour=(20, 180, 20))


def _rerun_succeeds(env: Env, result) -> None:
    """After the fault clears, the same command resumes and commits the new mesh."""
    env.monkeypatch.undo()
    again = env.onboard()
    assert again.rc == 0, again.err
    from faults.harness import rows

    assert any("new_cube" in r for r in rows(env.store)["meshes"])


def _failing_delta_writes(env: Env, code: int, after: int = 0) -> None:
    """Make the store's Delta writes fail as delta-rs reports an OS error (``... (os error N)``) after
    ``after`` successful table commits; the first failing write leaves a partial data file behind."""
    import deltalake

    real = deltalake.write_deltalake
    calls = {"n": 0}

    def write(target, *a, **k):
        calls["n"] += 1
        if calls["n"] <= after:
            return real(target, *a, **k)
        where = Path(str(getattr(target, "table_uri", target)).removeprefix("file://"))
        where.mkdir(parents=True, exist_ok=True)
        (where / "part-00000-partial.zstd.parquet").write_bytes(b"PAR1 partial")
        raise RuntimeError(
            f"Generic LocalFileSystem error: Unable to copy data to file: {os.strerror(code)} "
            f"(os error {code})"
        )

    env.monkeypatch.setattr(deltalake, "write_deltalake", write)


@case("onboard_disk_full_on_first_table", "onboard", "error", "no space left", check=_rerun_succeeds)
def _(env: Env):
    _new_mesh(env)
    _failing_delta_writes(env, errno.ENOSPC)
    return env.onboard()


@case("onboard_disk_full_mid_batch", "onboard", "error", "no space left", check=_rerun_succeeds)
def _(env: Env):
    _new_mesh(env)
    _failing_delta_writes(env, errno.ENOSPC, after=2)  # meshes and views committed, captions fail
    return env.onboard()


@case("onboard_read_only_data_dir", "onboard", "error", "read-only file system", check=_rerun_succeeds)
def _(env: Env):
    _new_mesh(env)
    _failing_delta_writes(env, errno.EROFS)
    return env.onboard()


# ================================================================== onboard: library faults
def lib_case(name: str, outcome: str, expect: str = "", extra=(), check=None):
    """A case that adds something to the library and runs onboarding over it."""

    def wrap(make):
        def act(env: Env):
            make(env.lib)
            return env.onboard(*extra)

        CASES.append(Case(f"onboard_{name}", "onboard", outcome, act, expect, check=check))
        return make

    return wrap


def _onboarded(*paths: str):
    """Check: these library paths have an active meshes row after the run."""

    def check(env: Env, result) -> None:
        from pipeline.store import Store

        with Store.open(env.store) as s:
            t = s.read_latest("meshes").to_pylist()
        active = {r["source_path"] for r in t if r["status"] == "active"}
        for p in paths:
            assert p in active, f"{p} not onboarded; active: {sorted(active)}"

    return check


@lib_case("dangling_symlink", "errors_row", "dangling symlink")
def _(lib: Path):
    os.symlink("nowhere.obj", lib / "x.obj")


@lib_case("symlink_loop", "errors_row", "symlink loop")
def _(lib: Path):
    os.symlink("x.obj", lib / "x.obj")


@lib_case("symlink_pair_loop", "errors_row", "symlink loop")
def _(lib: Path):
    os.symlink("b.obj", lib / "a.obj")
    os.symlink("a.obj", lib / "b.obj")


@lib_case("fifo_mesh", "errors_row", "FIFO")
def _(lib: Path):
    os.mkfifo(lib / "x.obj")


@lib_case("socket_mesh", "errors_row", "socket")
def _(lib: Path):
    s = socket.socket(socket.AF_UNIX)
    s.bind(str(lib / "x.stl"))
    s.close()


@lib_case("fifo_texture", "errors_row", "missing texture")
def _(lib: Path):
    write_textured_obj(lib / "fifo_tex")
    (lib / "fifo_tex" / "texture.png").unlink()
    os.mkfifo(lib / "fifo_tex" / "texture.png")


@lib_case("folder_symlink_loop", "errors_row", "followed once")
def _(lib: Path):
    (lib / "sub").mkdir()
    os.symlink("..", lib / "sub" / "up")


@lib_case("symlinked_folder", "handled", check=_onboarded("linked/model.obj"))
def _(lib: Path):
    write_textured_obj(lib.parent / "outside")
    os.symlink(lib.parent / "outside", lib / "linked")


@lib_case("symlinked_file", "handled", check=_onboarded("alias.ply"))
def _(lib: Path):
    os.symlink("sphere.ply", lib / "alias.ply")


@lib_case("folder_named_like_mesh", "handled")
def _(lib: Path):
    (lib / "folder.obj").mkdir()


@lib_case("non_utf8_file_name", "errors_row", "not valid UTF-8")
def _(lib: Path):
    data = (lib / "sphere.ply").read_bytes()
    with open(os.path.join(os.fsencode(lib), b"bad\xff.ply"), "wb") as fh:
        fh.write(data)


@lib_case("odd_file_name", "handled", check=_onboarded('it\'s a "cube"; drop table/model.obj'))
def _(lib: Path):
    write_textured_obj(lib / 'it\'s a "cube"; drop table')


def _png(width: int, height: int) -> bytes:
    """A PNG whose header claims ``width x height`` pixels over a tiny (invalid) body: a pixel bomb."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", ihdr)
        + chunk(b"IDAT", zlib.compress(b"\0" * 64))
        + chunk(b"IEND", b"")
    )


@lib_case("texture_corrupt", "errors_row", "cannot be decoded")
def _(lib: Path):
    write_textured_obj(lib / "bad_tex")
    data = (lib / "bad_tex" / "texture.png").read_bytes()
    (lib / "bad_tex" / "texture.png").write_bytes(data[: len(data) // 2])


@lib_case("texture_not_an_image", "errors_row", "cannot be decoded")
def _(lib: Path):
    write_textured_obj(lib / "txt_tex", texture=b"this is not a picture\n" * 20)


@lib_case("texture_pixel_bomb", "errors_row", "max-texture-pixels")
def _(lib: Path):
    write_textured_obj(lib / "bomb", texture=_png(20000, 20000))


@lib_case(
    "texture_over_custom_limit", "errors_row", "max-texture-pixels", extra=("--max-texture-pixels", "100")
)
def _(lib: Path):
    write_textured_obj(lib / "small_limit", colour=(20, 20, 20))


@lib_case("texture_missing", "errors_row", "missing texture")
def _(lib: Path):
    write_textured_obj(lib / "no_tex")
    (lib / "no_tex" / "texture.png").unlink()


@lib_case("material_missing", "errors_row", "missing material")
def _(lib: Path):
    write_textured_obj(lib / "no_mtl")
    (lib / "no_mtl" / "model.mtl").unlink()


@lib_case("obj_truncated_mid_line", "errors_row", "truncated")
def _(lib: Path):
    obj = write_textured_obj(lib / "cut")
    data = obj.read_bytes()
    obj.write_bytes(data[: data.rindex(b"/") + 1])  # cut inside the last face line


@lib_case("obj_dropped_faces", "errors_row", "face lines")
def _(lib: Path):
    (lib / "dropped.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 2\nf 1 3 4\n")


@lib_case("obj_vertex_out_of_range", "errors_row", "does not exist")
def _(lib: Path):
    (lib / "oor.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 1 2 99\n")


@lib_case("obj_empty", "errors_row", "empty mesh")
def _(lib: Path):
    (lib / "empty.obj").write_bytes(b"")


@lib_case("obj_nan_vertices", "errors_row", "non-finite")
def _(lib: Path):
    (lib / "nan.obj").write_text("v 0 0 0\nv nan 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 3 4\n")


@lib_case("ply_garbage", "errors_row", "cannot parse")
def _(lib: Path):
    (lib / "junk.ply").write_bytes(
        b"ply\nformat binary_little_endian 1.0\nelement vertex 99999\n" + b"\x07" * 64
    )


@lib_case("glb_garbage", "errors_row", "cannot parse")
def _(lib: Path):
    (lib / "junk.glb").write_bytes(b"glTF" + b"\x02" * 60)


@lib_case("stl_zero_bytes", "errors_row", "")
def _(lib: Path):
    (lib / "zero.stl").write_bytes(b"")


@lib_case("gltf_bad_json", "errors_row", "unreadable glTF")
def _(lib: Path):
    (lib / "bad.gltf").write_text("{not json")


def _during_render(action):
    """Run ``action(abs_path)`` just before the mesh at ``abs_path`` is rendered (a file changed mid-run)."""

    def prepare_patch(env: Env) -> None:
        from pipeline.onboard.stages.render import RenderStage

        real = RenderStage.render_one

        def render_one(self, item):
            action(Path(item["abs_path"]))
            return real(self, item)

        env.monkeypatch.setattr(RenderStage, "render_one", render_one)

    return prepare_patch


@case("onboard_file_deleted_during_run", "onboard", "errors_row", "deleted or moved during the run")
def _(env: Env):
    _new_mesh(env)
    _during_render(lambda p: p.unlink())(env)
    return env.onboard()


@case("onboard_texture_deleted_during_run", "onboard", "errors_row", "deleted during the run")
def _(env: Env):
    _new_mesh(env)
    _during_render(lambda p: (p.parent / "texture.png").unlink())(env)
    return env.onboard()


@case("onboard_hash_hangs", "onboard", "errors_row", "hung network mount")
def _(env: Env):
    import time

    import pipeline.mesh.discover as discover

    _new_mesh(env)
    real = discover.content_hash

    def slow(path, refs):
        if "new_cube" in str(path):
            time.sleep(3)
        return real(path, refs)

    env.monkeypatch.setattr(discover, "content_hash", slow)
    env.monkeypatch.setattr(discover, "HASH_TIMEOUT_S", 0.3)
    return env.onboard()


@case("onboard_unchanged_rerun", "onboard", "handled")
def _(env: Env):
    return env.onboard()


# ================================================================== query
_QUERY = ["--prompt", "the red box", "--box", "4,4,60,60", "--profile", "offline"]


def _photo(env: Env) -> Path:
    from PIL import Image

    p = env.tmp / "photo.png"
    Image.new("RGB", (96, 96), (200, 40, 40)).save(p)
    return p


def query_case(name: str, expect: str, argv_fn):
    def act(env: Env):
        return env.cli("query", ["--store", env.store, *argv_fn(env)])

    CASES.append(Case(f"query_{name}", "query", "error", act, expect))


for _name, _argv, _expect in [
    ("threads_negative", ["--threads", "-1"], ">= 1"),
    ("top_zero", ["--top", "0"], ">= 1"),
    ("threshold_nan", ["--threshold", "nan"], "finite"),
    ("threshold_out_of_range", ["--threshold", "7"], "<= 1"),
    ("fallback_k_zero", ["--fallback-k", "0"], ">= 1"),
    ("prompt_weight_negative", ["--prompt-weight", "-0.5"], ">= 0"),
]:
    option_error("query", f"query_{_name}", ["--image", "x.png", "--prompt", "x", *_argv], _expect)

query_case("image_missing", "image not found", lambda env: ["--image", env.tmp / "none.png", *_QUERY])
query_case(
    "image_not_an_image",
    "not an image",
    lambda env: ["--image", (env.tmp / "a.png").write_text("x") and env.tmp / "a.png", *_QUERY],
)
query_case(
    "box_outside_image",
    "box",
    lambda env: ["--image", _photo(env), "--prompt", "the box", "--box", "500,500,600,600"],
)
query_case(
    "box_not_numbers", "box", lambda env: ["--image", _photo(env), "--prompt", "the box", "--box", "a,b,c,d"]
)
query_case(
    "prompt_empty", "prompt", lambda env: ["--image", _photo(env), "--prompt", "  ", "--box", "4,4,60,60"]
)


@case("query_store_missing", "query", "error", "no store")
def _(env: Env):
    return env.cli("query", ["--store", env.tmp / "none", "--image", _photo(env), *_QUERY])


@case("query_store_is_a_file", "query", "error", "is a file")
def _(env: Env):
    (env.tmp / "f").write_text("x")
    return env.cli("query", ["--store", env.tmp / "f", "--image", _photo(env), *_QUERY])


@case("query_works", "query", "handled")
def _(env: Env):
    return env.cli("query", ["--store", env.store, "--image", _photo(env), *_QUERY, "--no-cache"])


# ================================================================== sql: the read-only surface
def _a_part(env: Env, table: str = "captions") -> Path:
    return sorted((env.store / table).glob("*.parquet"))[0]


def sql_case(name: str, outcome: str, expect: str, sql_fn, extra=(), check=None):
    def act(env: Env):
        return env.sql(*extra(env) if callable(extra) else extra, "-c", sql_fn(env))

    CASES.append(Case(f"sql_{name}", "sql", outcome, act, expect, check=check))


sql_case(
    "copy_over_committed_part",
    "error",
    "refused",
    lambda env: f"COPY (SELECT * FROM captions_all LIMIT 1) TO '{_a_part(env)}' (FORMAT parquet)",
)
sql_case(
    "copy_forges_log_entry",
    "error",
    "refused",
    lambda env: f"COPY (SELECT 1 AS seq) TO '{env.store}/_log/999999999999.json'",
)
sql_case(
    "copy_over_part_with_export_dir",
    "error",
    "writes only under --export-dir",
    lambda env: f"COPY (SELECT 1) TO '{_a_part(env)}' (FORMAT parquet)",
    extra=lambda env: ["--export-dir", env.tmp / "out"],
)
sql_case(
    "copy_dotdot_escape",
    "error",
    "refused",
    lambda env: f"COPY (SELECT 1) TO '{env.tmp}/out/../store/x.csv'",
    extra=lambda env: ["--export-dir", env.tmp / "out"],
)
sql_case("read_csv_host_file", "error", "refused", lambda env: "SELECT * FROM read_csv('/etc/passwd')")
sql_case("read_text_host_file", "error", "refused", lambda env: "SELECT * FROM read_text('/etc/hostname')")
sql_case("glob_host_files", "error", "refused", lambda env: "SELECT * FROM glob('/etc/*')")
sql_case(
    "read_parquet_store_part", "error", "refused", lambda env: f"SELECT * FROM read_parquet('{_a_part(env)}')"
)
sql_case(
    "attach_and_create_table",
    "error",
    "ATTACH refused",
    lambda env: f"ATTACH '{env.tmp}/evil.db' AS evil; CREATE TABLE evil.t AS SELECT 1",
)
sql_case("attach_store_file", "error", "ATTACH refused", lambda env: f"ATTACH '{_a_part(env)}' AS p")
sql_case("install_extension", "error", "INSTALL refused", lambda env: "INSTALL httpfs")
sql_case("load_extension", "error", "LOAD refused", lambda env: "LOAD httpfs")
sql_case("set_setting", "error", "SET refused", lambda env: "SET enable_external_access = true")
sql_case("reset_setting", "error", "refused", lambda env: "RESET lock_configuration")
sql_case("pragma_setting", "error", "refused", lambda env: "PRAGMA threads = 1")
sql_case("export_database", "error", "EXPORT DATABASE refused", lambda env: f"EXPORT DATABASE '{env.tmp}/x'")
sql_case("import_database", "error", "refused", lambda env: f"IMPORT DATABASE '{env.tmp}'")
sql_case(
    "create_secret",
    "error",
    "CREATE SECRET refused",
    lambda env: "CREATE SECRET (TYPE s3, KEY_ID 'a', SECRET 'b')",
)
sql_case(
    "copy_without_export_dir",
    "error",
    "needs --export-dir",
    lambda env: f"COPY (SELECT 1) TO '{env.tmp}/a.csv'",
)
sql_case("syntax_error", "error", "syntax", lambda env: "SELEC nonsense FROM")
sql_case("unknown_table", "error", "does not exist", lambda env: "SELECT * FROM no_such_table")
sql_case(
    "memory_table_is_fine", "handled", "", lambda env: "CREATE TABLE t AS SELECT 1 AS a; SELECT * FROM t"
)
sql_case("set_variable_is_fine", "handled", "", lambda env: "SET VARIABLE audit_min_caption_chars = 3")


def _exported(env: Env, result) -> None:
    assert (env.tmp / "out" / "captions.parquet").is_file()


sql_case(
    "copy_into_export_dir",
    "handled",
    "",
    lambda env: f"COPY (SELECT mesh_id, caption FROM captions_all) TO '{env.tmp}/out/captions.parquet'",
    extra=lambda env: ["--export-dir", env.tmp / "out"],
    check=_exported,
)


@case("sql_export_dir_inside_store", "sql", "error", "overlaps the store")
def _(env: Env):
    return env.sql("--export-dir", env.store / "captions", "-c", "SELECT 1")


@case("sql_export_dir_contains_store", "sql", "error", "overlaps the store")
def _(env: Env):
    return env.sql("--export-dir", env.tmp, "-c", "SELECT 1")


@case("sql_export_duckdb_into_store", "sql", "error", "inside the store")
def _(env: Env):
    return env.sql("--export-duckdb", _a_part(env), "--force")


@case("sql_shell_attach_refused", "sql", "handled", check=lambda env, r: None)
def _(env: Env):
    r = env.sql(stdin=f"ATTACH '{env.tmp}/evil.db' AS e;\nSELECT count(*) FROM meshes_all;\n")
    assert r.rc == 1 and "ATTACH refused" in r.err and not (env.tmp / "evil.db").exists()
    r.rc = 0  # the shell reports the failed statement and goes on
    return r


for _name, _argv, _expect in [
    ("max_width_negative", ["--max-width", "-1", "-c", "SELECT 1"], ">= 0"),
    ("set_without_value", ["--set", "novalue", "-c", "SELECT 1"], "NAME=VALUE"),
    ("unknown_audit", ["--audit", "nonsense"], "no audit"),
    ("unknown_format", ["--format", "xml", "-c", "SELECT 1"], "invalid choice"),
]:
    option_error("sql", f"sql_{_name}", _argv, _expect)


@case("sql_file_missing", "sql", "error", "no such file")
def _(env: Env):
    return env.sql("-f", env.tmp / "none.sql")


@case("sql_store_missing", "sql", "error", "no store")
def _(env: Env):
    return env.cli("sql", [env.tmp / "none", "-c", "SELECT 1"])


# ================================================================== compact
@case("compact_store_missing", "compact", "error", "no store")
def _(env: Env):
    return env.cli("compact", [env.tmp / "none"])


@case("compact_store_is_a_file", "compact", "error", "is a file")
def _(env: Env):
    (env.tmp / "f").write_text("x")
    return env.cli("compact", [env.tmp / "f"])


@case("compact_locked", "compact", "error", "locked by another writer")
def _(env: Env):
    from pipeline.store import Store

    with Store.open(env.store, writable=True):
        return env.cli("compact", [env.store])


@case("compact_read_only", "compact", "error", "read-only file system")
def _(env: Env):
    _fail_os_open(env, "_lock", errno.EROFS)
    return env.cli("compact", [env.store])


@case("compact_disk_full", "compact", "error", "no space left", rows="latest")
def _(env: Env):
    import pipeline.compact

    _failing_delta_writes(env, errno.ENOSPC)
    # as if rows were superseded: compact must rewrite the table, and the disk is full
    env.monkeypatch.setattr(pipeline.compact, "superseded", lambda store, dataset: 1)
    return env.cli("compact", [env.store])


@case("compact_works", "compact", "handled", rows="latest")
def _(env: Env):
    return env.cli("compact", [env.store])


@case("compact_twice", "compact", "handled", rows="latest")
def _(env: Env):
    first = env.cli("compact", [env.store])
    assert first.rc == 0, first.err
    return env.cli("compact", [env.store])


# ================================================================== evaluate
for _name, _argv, _expect in [
    ("taus_zero_step", ["--queries", "q.jsonl", "--taus", "0:1:0"], "STEP > 0"),
    ("taus_nan", ["--queries", "q.jsonl", "--taus", "0.1,nan"], "finite"),
    ("top_ks_zero", ["--queries", "q.jsonl", "--top-ks", "0,5"], ">= 1"),
    ("gallery_negative", ["--queries", "q.jsonl", "--gallery", "-1"], ">= 0"),
    ("synthetic_zero", ["--synthetic", "0"], ">= 1"),
    ("bop_visib_out_of_range", ["--queries", "q.jsonl", "--bop-min-visib", "2"], "<= 1"),
]:
    option_error("evaluate", f"evaluate_{_name}", _argv, _expect)


# ================================================================== store corruption (issue 10 item 5)
# A damaged store must give a one-line error that names the file, and no command may delete or rewrite
# files on the word of a damaged log.
def _data_file(env: Env, table: str = "captions") -> Path:
    """One committed data file of ``table`` (a Parquet file in the table's folder)."""
    return sorted((env.store / table).rglob("*.parquet"))[0]


def _log_entry(env: Env) -> Path:
    """The newest commit-log entry (the store's own log, or a Delta table's ``_delta_log``)."""
    logs = sorted((env.store / "_log").glob("*.json")) or sorted(env.store.rglob("_delta_log/*.json"))
    return logs[-1]


def store_case(name: str, tool: str, damage, argv_fn, outcome="error", expect="", marks=(), rows="skip"):
    def act(env: Env):
        return env.cli(tool, [str(a) for a in argv_fn(env)])

    def prepare(env: Env):
        damage(env)

    CASES.append(
        Case(f"{tool}_{name}", tool, outcome, act, expect, prepare=prepare, rows=rows, marks=list(marks))
    )


def _count_captions(env: Env):
    return [env.store, "-c", "SELECT count(*) FROM captions_all"]


def _compact(env: Env):
    return [env.store]


store_case("store_marker_deleted", "sql", lambda env: _marker(env).unlink(), _count_captions, expect="store")
# compact rewrites tables one by one (rows kept, superseded dropped) before it meets the damage
store_case(
    "store_part_deleted",
    "compact",
    lambda env: _data_file(env).unlink(),
    _compact,
    expect="part-",
    rows="latest",
)
store_case(
    "store_part_deleted",
    "sql",
    lambda env: _data_file(env).unlink(),
    _count_captions,
    expect="part-",
)
store_case(
    "store_part_truncated",
    "sql",
    lambda env: _data_file(env).write_bytes(_data_file(env).read_bytes()[:100]),
    _count_captions,
    expect="part-",
)
store_case(
    "store_log_entry_empty",
    "sql",
    lambda env: _log_entry(env).write_bytes(b""),
    _count_captions,
    expect=".json",
)
store_case(
    "store_part_swapped_with_other_table",
    "sql",
    lambda env: _data_file(env).write_bytes(_data_file(env, "runs").read_bytes()),
    _count_captions,
    expect="part-",
)


def _marker(env: Env) -> Path:
    from pipeline.store import STORE_MARKER

    return env.store / STORE_MARKER


def _delete_captions_log(env: Env) -> None:
    """Delete the captions table's only commit: its data files are then named by no commit."""
    env.kept = sorted((env.store / "captions").glob("*.parquet"))
    for entry in (env.store / "captions" / "_delta_log").glob("*.json"):
        entry.unlink()


def _files_kept(env: Env, result) -> None:
    """Nothing is deleted on the word of a damaged log: the lost commit's data files are still there."""
    assert env.kept and all(p.exists() for p in env.kept)


@case(
    "onboard_store_log_entry_deleted",
    "onboard",
    "handled",
    prepare=_delete_captions_log,
    rows="skip",
    check=_files_kept,
)
def _(env: Env):
    return env.onboard()  # re-captions (the table looks empty) and must not delete the old data files


# ================================================================== readers on a read-only store
def _read_only_store(env: Env) -> None:
    """Every write below the store fails with EROFS (a read-only mount), reads work."""
    real_open, real_replace, real_mkdir = os.open, os.replace, os.mkdir
    store = str(env.store)

    def ro_open(path, flags, *a, **k):
        if str(path).startswith(store) and flags & (os.O_WRONLY | os.O_RDWR | os.O_CREAT):
            raise OSError(errno.EROFS, "Read-only file system", str(path))
        return real_open(path, flags, *a, **k)

    def ro_two(real):
        def fake(src, *a, **k):
            if str(src).startswith(store):
                raise OSError(errno.EROFS, "Read-only file system", str(src))
            return real(src, *a, **k)

        return fake

    env.monkeypatch.setattr(os, "open", ro_open)
    env.monkeypatch.setattr(os, "replace", ro_two(real_replace))
    env.monkeypatch.setattr(os, "mkdir", ro_two(real_mkdir))


@case("sql_read_only_store", "sql", "handled")
def _(env: Env):
    _read_only_store(env)
    r = env.sql("--audit", "all")
    assert "audit" in r.out, r.out[:300]
    return r


@case("query_read_only_store", "query", "handled")
def _(env: Env):
    photo = _photo(env)
    _read_only_store(env)
    return env.cli("query", ["--store", env.store, "--image", photo, *_QUERY])


store_case(
    "store_part_deleted",
    "query",
    lambda env: _data_file(env).unlink(),
    lambda env: ["--store", env.store, "--image", _photo(env), *_QUERY],
    expect="part-",
)


@case(
    "onboard_store_part_deleted",
    "onboard",
    "error",
    "part-",
    prepare=lambda env: _data_file(env, "meshes").unlink(),
    rows="skip",
)
def _(env: Env):
    return env.onboard()
