"""Hostile round three (issue 36): folders the tool did not write, read by `runs`, `report DIR`,
`status` and `lineage`; two sweeps into one folder; spreadsheet formulas in `runs --csv`.

Every reader of a user-given run folder goes through ``engine/jsonio.py`` (regular files only,
size, nesting and numbers bounded). The hang cases run the CLI in a subprocess with a timeout
and an address-space limit (a symlink to /dev/zero read to its end would eat the machine's
memory); the seeded fuzz test runs its commands in one such subprocess, each under an alarm.
Each test here fails on aaaa9c0.
"""

from __future__ import annotations

import csv
import io
import json
import os
import random
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import ROOT, cli, json_paths, make_toy_input

TOY = ("--pipeline", "toy")
TIMEOUT = float(os.environ.get("GCVD_HANG_TIMEOUT", "60"))  # s for a command that must not hang (~1-3 s)
MEMORY = 3 << 30  # address space of a command under test: enough for numpy + matplotlib
SEED = int(os.environ.get("GCVD_FUZZ_SEED", "36"))
SCALE = int(os.environ.get("GCVD_FUZZ_SCALE", "1"))
RUNS = ("threshold.cut=10", "threshold.cut=20")


def _limit_memory() -> None:  # in the child, before exec
    resource.setrlimit(resource.RLIMIT_AS, (MEMORY, MEMORY))


def bounded(*args: str, cwd: Path | None = None, env: dict | None = None) -> subprocess.CompletedProcess:
    """`python -m gcvd_flow ARGS` with a timeout (TimeoutExpired fails the test) and a memory limit."""
    e = dict(os.environ, OMP_NUM_THREADS="1", **(env or {}))
    p = subprocess.run([sys.executable, "-m", "gcvd_flow", *map(str, args)], capture_output=True,
                       timeout=TIMEOUT, cwd=cwd or ROOT, env=e, preexec_fn=_limit_memory)
    # decoded without newline translation: a CR inside a CSV cell stays a CR
    return subprocess.CompletedProcess(p.args, p.returncode, p.stdout.decode(errors="replace"),
                                       p.stderr.decode(errors="replace"))


def one_line_error(p: subprocess.CompletedProcess, *fragments: str) -> str:
    assert p.returncode == 2, (p.returncode, p.stdout, p.stderr)
    lines = [ln for ln in p.stderr.splitlines() if ln.strip() and not ln.startswith("warning:")]
    assert len(lines) == 1 and "Traceback" not in p.stderr, p.stderr
    assert lines[0].startswith("gcvd-flow: error: "), p.stderr
    for f in fragments:
        assert f in lines[0], (f, lines[0])
    return lines[0]


def clean_exit_0(p: subprocess.CompletedProcess) -> None:
    assert p.returncode == 0 and "Traceback" not in p.stderr, (p.returncode, p.stderr)


@pytest.fixture(scope="module")
def made(tmp_path_factory) -> dict[str, Path]:
    """A toy sweep of two runs (threshold.cut=10, 20) with metrics.json, made once."""
    d = tmp_path_factory.mktemp("untrusted")
    inp = make_toy_input(d / "in", n=6)
    cli("sweep", str(inp), "--out", str(d / "sw"), "--cache", str(d / "cache"), *TOY,
        "--grid", "threshold.cut=10,20", check=True)
    for name, ate in zip(RUNS, (0.2, 0.1)):
        (d / "sw" / name / "metrics.json").write_text(json.dumps({"ate_rmse": ate, "abs_rel": ate / 2}))
    return {"dir": d, "input": inp, "cache": d / "cache", "sw": d / "sw"}


def copy_sweep(made: dict[str, Path], dst: Path) -> Path:
    shutil.copytree(made["sw"], dst, symlinks=True)
    return dst


def index_of(folder: Path) -> str:
    return (folder / "index.html").read_text()


# ------------------------------------------------------------------------------ hangs


@pytest.mark.parametrize("what", ["run.json", "metrics.json", "sweep.json"])
def test_fifo_in_a_run_folder_does_not_hang_runs_or_report(made, tmp_path, what):
    sw = copy_sweep(made, tmp_path / "sw")
    target = sw / what if what == "sweep.json" else sw / RUNS[0] / what
    target.unlink()
    os.mkfifo(target)
    p = bounded("runs", sw)
    one_line_error(p, str(target.name), "not a regular file")
    p = bounded("report", sw)
    clean_exit_0(p)
    page = index_of(sw)
    assert RUNS[1] in page and "not a regular file" in page, p.stderr
    if what != "sweep.json":  # that run is listed as broken, the other one is in the table
        assert "Broken runs (1)" in page and f"<code>{RUNS[0]}</code>" in page


@pytest.mark.parametrize("what", ["run.json", "metrics.json", "sweep.json"])
def test_symlink_to_dev_zero_is_not_read(made, tmp_path, what):
    sw = copy_sweep(made, tmp_path / "sw")
    target = sw / what if what == "sweep.json" else sw / RUNS[1] / what
    target.unlink()
    target.symlink_to("/dev/zero")
    for args in (("runs", sw), ("runs", sw, "--csv")):
        one_line_error(bounded(*args), target.name, "not a regular file")
    clean_exit_0(bounded("report", sw))


def test_oversized_file_is_refused_unread(made, tmp_path):
    sw = copy_sweep(made, tmp_path / "sw")
    big = sw / RUNS[0] / "metrics.json"
    with open(big, "r+b") as f:  # sparse: 1 GB that a reader would have to hold in memory
        f.truncate(1 << 30)
    one_line_error(bounded("runs", sw), "metrics.json", "larger than")


# ------------------------------------------------------------------------------ numbers


@pytest.mark.parametrize("number,why", [("9" * 5000, "5000 digits"), ("1e999", "out of range"),
                                        (str(10 ** 400), "401 digits")])
def test_out_of_range_numbers_are_one_line_not_a_traceback(made, tmp_path, number, why):
    """In a run's stage counts (run.json, no sweep.json) and in its metrics (`runs --sort`)."""
    sw = copy_sweep(made, tmp_path / "sw")
    (sw / "sweep.json").unlink()  # the stage counts come from run.json
    run = sw / RUNS[0] / "run.json"
    doc = json.loads(run.read_text())
    doc["counts"]["decode"]["executed"] = "@@"
    run.write_text(json.dumps(doc).replace('"@@"', number))
    for args in (("runs", sw), ("runs", sw, "--sort", "ate_rmse"), ("runs", sw, "--csv")):
        one_line_error(bounded(*args), str(run), why)
    p = bounded("report", sw)
    clean_exit_0(p)
    assert "Broken runs (1)" in index_of(sw) and why in index_of(sw)
    run.write_text(json.dumps(json.loads(json.dumps(doc).replace('"@@"', "6"))))  # repaired
    (sw / RUNS[1] / "metrics.json").write_text('{"ate_rmse": %s, "abs_rel": 0.1}' % number)
    for args in (("runs", sw, "--sort", "ate_rmse"), ("runs", sw, "--sort=-ate_rmse")):
        one_line_error(bounded(*args), "metrics.json", why)
    clean_exit_0(bounded("report", sw))


def test_infinite_and_nan_metrics_are_shown_not_plotted(made, tmp_path):
    """NaN / Infinity are what Python's json writes for such a float: accepted, never a traceback."""
    sw = copy_sweep(made, tmp_path / "sw")
    (sw / RUNS[0] / "metrics.json").write_text('{"ate_rmse": Infinity, "abs_rel": NaN}')
    p = bounded("runs", sw, "--sort", "ate_rmse", "--json")
    clean_exit_0(p)
    assert [r["name"] for r in json.loads(p.stdout)["runs"]] == [RUNS[1], RUNS[0]]
    clean_exit_0(bounded("report", sw))
    assert "inf" in index_of(sw)


# ------------------------------------------------------------------------------ report DIR


def test_one_bad_run_does_not_hide_the_others_in_the_index(made, tmp_path):
    sw = copy_sweep(made, tmp_path / "sw")
    (sw / RUNS[0] / "run.json").write_text("{")
    p = bounded("report", sw)
    clean_exit_0(p)
    page = index_of(sw)
    assert "Broken runs (1)" in page and f"<code>{RUNS[0]}</code>" in page and "run.json" in page
    assert f"{RUNS[1]} (no report)" in page  # the other run, in the table
    assert f"warning: {RUNS[0]}: broken" in p.stderr
    one_line_error(bounded("runs", sw), "run.json")  # the table alone still refuses (exit 2)


@pytest.mark.parametrize("doc", [[1, 2], {"grid": 5}, {"grid": [5, {"key": [1], "values": 7}]},
                                 {"grid": [{"key": "a", "values": "xyz"}], "sets": "s", "input": {"a": 1},
                                  "profile": 3, "runs": {"a": 1}},
                                 {"runs": [1, {"name": RUNS[0], "stages": [{"executed": "x"}, 5]},
                                           {"name": RUNS[1], "stages": 7}]}, "nesting"])
def test_wrong_shape_sweep_json(made, tmp_path, doc):
    sw = copy_sweep(made, tmp_path / "sw")
    (sw / "sweep.json").write_text("[" * 100_000 + "]" * 100_000 if doc == "nesting" else json.dumps(doc))
    p = bounded("report", sw)
    clean_exit_0(p)
    assert RUNS[0] in index_of(sw) and RUNS[1] in index_of(sw)
    p = bounded("runs", sw)
    if doc == "nesting":
        one_line_error(p, "sweep.json", "nested deeper")
    else:
        clean_exit_0(p)


def test_mathtext_in_a_parameter_value_is_shown_as_text(made, tmp_path):
    sw = copy_sweep(made, tmp_path / "sw")
    for name, label in zip(RUNS, ("$\\foo$", "$x^2$ $")):
        p = sw / name / "run.json"
        doc = json.loads(p.read_text())
        doc["config"]["threshold"]["label"] = label
        doc["config"]["$\\bar$"] = label  # in the key (the x axis label) too
        p.write_text(json.dumps(doc))
    clean_exit_0(bounded("report", sw))
    page = index_of(sw)
    assert "$\\foo$" in page and page.count("<img class='plot'") == 3  # cut, label, $\bar$


def test_report_to_a_directory_names_it(made, tmp_path):
    sw = copy_sweep(made, tmp_path / "sw")
    (tmp_path / "pages").mkdir()
    line = one_line_error(bounded("report", sw, "--to", tmp_path / "pages"), str(tmp_path / "pages"),
                          "is a directory")
    assert ".tmp-" not in line and not list(tmp_path.glob(".pages*"))  # no temp file left either


# ------------------------------------------------------------------------------ status / lineage caches


def test_lineage_cache_missing_is_not_created(made, tmp_path):
    missing = tmp_path / "MISSING"
    one_line_error(bounded("lineage", made["sw"] / RUNS[0], "--cache", missing), str(missing), "does not exist")
    assert not missing.exists()
    one_line_error(bounded("lineage", "0" * 64, "--cache", missing), str(missing))
    assert not missing.exists()
    p = bounded("lineage", made["sw"] / RUNS[0], "--cache", made["cache"])
    clean_exit_0(p)
    assert "threshold" in p.stdout


def test_status_creates_no_cache_where_run_json_points(made, tmp_path):
    run = shutil.copytree(made["sw"] / RUNS[0], tmp_path / "run")
    doc = json.loads((run / "run.json").read_text())
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    for where in (elsewhere, tmp_path / "nope"):
        doc["cache"] = str(where)
        (run / "run.json").write_text(json.dumps(doc))
        for verb in (("status", "--out", run), ("why", "threshold", "--out", run), ("lineage", run)):
            bounded(*verb, env={"GCVD_FLOW_CACHE": str(made["cache"])})
        assert not (tmp_path / "nope").exists() and os.listdir(elsewhere) == [], os.listdir(elsewhere)
    doc["cache"] = str(made["cache"])  # a real cache is still used
    (run / "run.json").write_text(json.dumps(doc))
    p = bounded("status", "--out", run, env={"GCVD_FLOW_CACHE": str(tmp_path / "default")})
    clean_exit_0(p)
    assert "up to date" in p.stdout and not (tmp_path / "default").exists()


# ------------------------------------------------------------------------------ runs --csv


def test_csv_escapes_formula_prefixes_in_text_cells(made, tmp_path):
    root = tmp_path / "runs"
    root.mkdir()
    names = ['=HYPERLINK("evil","click")', "+SUM(A1)", "-cmd", "@A1", "\tx", "\rx", "plain"]
    for i, name in enumerate(names):
        run = shutil.copytree(made["sw"] / RUNS[0], root / name)
        doc = json.loads((run / "run.json").read_text())
        doc["config"]["threshold"]["label"] = name  # a text parameter
        doc["config"]["threshold"]["offset"] = -i  # a number: stays a number
        (run / "run.json").write_text(json.dumps(doc))
        (run / "metrics.json").write_text(json.dumps({"ate_rmse": -0.5 * i, "=cmd|' /C calc'!A0": 1}))
    p = bounded("runs", root, "--csv")
    clean_exit_0(p)
    rows = list(csv.reader(io.StringIO(p.stdout, newline="")))
    head, body = rows[0], rows[1:]
    assert "'=cmd|' /C calc'!A0" in head
    col = {h: i for i, h in enumerate(head)}
    by_name = {r[0]: r for r in body}
    assert sorted(by_name) == sorted("'" + n if n != "plain" else n for n in names), list(by_name)
    for n in names:
        r = by_name["'" + n if n != "plain" else n]
        assert r[col["threshold.label"]] == r[0]
        i = names.index(n)
        assert r[col["threshold.offset"]] == str(-i) and r[col["ate_rmse"]] == (f"{-0.5 * i:.4g}")
    for cell in (c for r in body for c in r):
        assert not cell.startswith(("=", "+", "@", "\t", "\r")) and not (cell.startswith("-") and
                                                                         not cell[1:2].isdigit()), cell


# ------------------------------------------------------------------------------ two sweeps, one folder


def test_second_sweep_into_the_same_folder_exits_2(made, tmp_path):
    out, cache = tmp_path / "sw", tmp_path / "cache"
    env = dict(os.environ, OMP_NUM_THREADS="1", GCVD_FLOW_JOBS="1")
    first = subprocess.Popen([sys.executable, "-m", "gcvd_flow", "sweep", str(made["input"]), "--out", str(out),
                              "--cache", str(cache), *TOY, "--set", "threshold.sleep=4",
                              "--grid", "threshold.cut=10,20", "--json"],
                             cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        t0 = time.time()
        while not (out / "sweep.json").exists() and time.time() - t0 < TIMEOUT:
            time.sleep(0.05)
        assert (out / "sweep.json").exists(), first.stderr
        second = bounded("sweep", made["input"], "--out", out, "--cache", cache, *TOY,
                         "--grid", "threshold.cut=10,30", env={"GCVD_FLOW_JOBS": "1"})
        assert first.poll() is None, "the first sweep ended before the second one started: raise its sleep"
        one_line_error(second, str(out), "another sweep")
        stdout, stderr = first.communicate(timeout=TIMEOUT)
    finally:
        if first.poll() is None:
            first.kill()
    assert first.returncode == 0, stderr
    rows = json.loads(stdout)["runs"]
    doc = json.loads((out / "sweep.json").read_text())
    assert doc["state"] == "done" and [g["values"] for g in doc["grid"]] == [[10, 20]]
    assert sorted(p.name for p in out.iterdir() if p.is_dir()) == list(RUNS)
    for row in doc["runs"]:  # sweep.json and --json describe the run directories as they are
        cfg = json.loads((Path(row["out"]) / "run.json").read_text())["config"]
        assert cfg["threshold"]["cut"] == row["params"]["threshold.cut"]
    assert [r["name"] for r in rows] == [r["name"] for r in doc["runs"]] == list(RUNS)
    clean_exit_0(bounded("sweep", made["input"], "--out", out, "--cache", cache, *TOY,
                         "--grid", "threshold.cut=10,30", env={"GCVD_FLOW_JOBS": "1"}))  # after it: fine


# ------------------------------------------------------------------------------ fuzz


DRIVER = r"""
import contextlib, io, json, signal, sys
from gcvd_flow.cli import main

class Hang(BaseException):  # not an Exception: main() must not catch it
    pass

def alarm(signum, frame):
    raise Hang()

signal.signal(signal.SIGALRM, alarm)
cases = json.load(open(sys.argv[1]))
with open(sys.argv[2], "w") as res:
    for n, args in enumerate(cases):
        out, err = io.StringIO(), io.StringIO()
        signal.alarm(int(sys.argv[3]))
        try:
            with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
                try:
                    code = main(args)
                except SystemExit as exc:
                    code = int(exc.code or 0)
        except Hang:
            code = "hang"
        finally:
            signal.alarm(0)
        res.write(json.dumps({"n": n, "code": code, "err": err.getvalue()[-4000:]}) + "\n")
        res.flush()
"""

HUGE = ["9" * 5000, "1e999", "-1e999", str(10 ** 400), "NaN", "Infinity", "-Infinity", "1e-999"]
VALUES = [None, True, 0, -1, 1.5, "x", "=1+1", "$\\foo$", "../../etc", [], {}, [1, "a"], {"a": {"b": [1]}}]


def mutate_json(doc, rng: random.Random) -> str:
    """JSON text of ``doc`` with one node replaced by another kind of value or an out-of-range
    number (as text: JSON can spell 1e999, Python cannot)."""
    doc = json.loads(json.dumps(doc))
    paths = json_paths(doc)
    path = rng.choice([p for p in paths if len(p) <= 3] if rng.random() < 0.7 else paths)
    marker = "@@MUT@@"
    huge = rng.random() < 0.4
    new = marker if huge else rng.choice(VALUES)
    if not path:
        text = json.dumps(new)
    else:
        node = doc
        for k in path[:-1]:
            node = node[k]
        if isinstance(node, dict) and rng.random() < 0.15:
            del node[path[-1]]
        else:
            node[path[-1]] = new
        text = json.dumps(doc)
    return text.replace(f'"{marker}"', rng.choice(HUGE))


def corrupt(target: Path, doc, rng: random.Random) -> str:
    """Replace ``target`` by something hostile; returns what, for the failure message."""
    kind = rng.choice(["json"] * 8 + ["fifo", "zero", "urandom", "dangling", "loop", "dir", "sparse", "bytes",
                                      "deep", "truncated", "empty", "utf16", "counts"])
    if target.is_symlink() or target.exists():
        shutil.rmtree(target) if target.is_dir() and not target.is_symlink() else target.unlink()
    if kind == "counts" and target.name == "run.json":  # wrong types in the stage counts
        doc = json.loads(json.dumps(doc))
        doc["counts"][rng.choice(list(doc["counts"]))][rng.choice(["executed", "cached"])] = \
            rng.choice(VALUES + [-5, 2.5, 1e300])
        target.write_text(json.dumps(doc))
    elif kind in ("json", "counts"):
        target.write_text(mutate_json(doc, rng))
    elif kind == "fifo":
        os.mkfifo(target)
    elif kind in ("zero", "urandom"):
        target.symlink_to(f"/dev/{kind}")
    elif kind == "dangling":
        target.symlink_to(target.parent / "no-such-file")
    elif kind == "loop":
        target.symlink_to(target)
    elif kind == "dir":
        target.mkdir()
    elif kind == "sparse":
        with open(target, "wb") as f:
            f.write(b'{"a": [')
            f.truncate(1 << 30)
    elif kind == "bytes":
        target.write_bytes(bytes(rng.randrange(256) for _ in range(rng.randrange(1, 200))))
    elif kind == "deep":
        target.write_text("{\"a\":" * 50_000 + "1" + "}" * 50_000)
    elif kind == "truncated":
        text = json.dumps(doc)
        target.write_text(text[:rng.randrange(1, max(2, len(text)))])
    elif kind == "empty":
        target.write_text("")
    elif kind == "utf16":
        target.write_bytes(json.dumps(doc).encode("utf-16"))
    return kind


def test_fuzz_run_folder_contents(made, tmp_path):
    """Seeded: each case is a copy of the sweep folder with one to three of its JSON files
    (run.json, metrics.json, sweep.json) replaced by wrong-shape / out-of-range / deep / corrupt
    JSON or a non-regular file; `runs`, `runs --sort`, `runs --csv`, `report DIR` and `status`
    must end in exit 0 or a one-line exit 2, never a traceback, never a hang."""
    rng = random.Random(SEED)
    sw = made["sw"]
    docs = {"sweep.json": json.loads((sw / "sweep.json").read_text())}
    for name in RUNS:
        for f in ("run.json", "metrics.json"):
            docs[f"{name}/{f}"] = json.loads((sw / name / f).read_text())
    cases, what = [], []
    for n in range(12 * SCALE):
        folder = copy_sweep(made, tmp_path / f"case{n}")
        done = []
        for rel in rng.sample(sorted(docs), rng.randint(1, 3)):
            done.append(f"{rel}: {corrupt(folder / rel, docs[rel], rng)}")
        for args in (["runs", folder], ["runs", folder, "--sort=" + rng.choice(["ate_rmse", "-abs_rel"])],
                     ["runs", folder, "--csv"], ["report", folder], ["status", "--out", folder / RUNS[n % 2]]):
            cases.append([str(a) for a in args])
            what.append("; ".join(done))
    (tmp_path / "cases.json").write_text(json.dumps(cases))
    per_case = 30
    env = dict(os.environ, OMP_NUM_THREADS="1", GCVD_FLOW_CACHE=str(tmp_path / "default-cache"),
               PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    p = subprocess.run([sys.executable, "-c", DRIVER, str(tmp_path / "cases.json"), str(tmp_path / "res.jsonl"),
                        str(per_case)], capture_output=True, text=True, cwd=tmp_path, env=env,
                       timeout=per_case * len(cases) + 60, preexec_fn=_limit_memory)
    results = [json.loads(ln) for ln in (tmp_path / "res.jsonl").read_text().splitlines()]
    assert p.returncode == 0 and len(results) == len(cases), (p.returncode, p.stderr[-3000:], len(results))
    codes = {0: 0, 2: 0}
    for r in results:
        args, err = cases[r["n"]], r["err"]
        where = f"{' '.join(args)} [{what[r['n']]}]"
        assert r["code"] != "hang", f"hang: {where}"
        assert "Traceback" not in err and "internal error" not in err, f"{where}\n{err}"
        assert r["code"] in (0, 2), f"{where}: exit {r['code']}\n{err}"
        if r["code"] == 2:
            lines = [ln for ln in err.splitlines() if ln.strip() and not ln.startswith("warning:")]
            assert len(lines) == 1 and lines[0].startswith("gcvd-flow: error: "), f"{where}\n{err}"
        codes[r["code"]] += 1
    assert codes[0] and codes[2], codes  # both outcomes reached: the cases are neither all fine nor all refused
    assert not (tmp_path / "default-cache").exists() or not any((tmp_path / "default-cache" / "objects").iterdir())
