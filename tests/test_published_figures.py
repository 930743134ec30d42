"""Every published re-test figure comes from a committed file.

A table whose line above is ``<!-- figures: KEY=PATH ... -->`` is checked cell by cell against the JSONs it names:
``rollouts=`` / ``plans=`` (written by ``adaptdiffuser evaluate-kept --into``; a row's first backticked word names its
key) and, for a "committed" column, ``committed-rollouts=`` / ``committed-plans=`` (the science runs' summaries). Each
column's meaning comes from its header; every number in a cell must be the one its JSON gives, rounded as printed (1
decimal for scores and gains, 2 for win rates, integers for seeds), in order, and nothing else. Every ``x [a, b]`` in
the prose of the same section must be one of those JSONs' intervals, or one of a pipeline record's that the marker
names as ``record-<name>=PATH`` (a science summary: its phases' scores, controls and gains, own and held out). The
checker is tested on tampered copies too.

A table whose line above is ``<!-- summary: PATH per-seed=FOLDER -->`` is a pipeline record's (a science summary, one
task, and its per-seed task metrics): one row per phase and set of start states, checked the same way.
"""

from __future__ import annotations

import json
import re
import subprocess
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import pytest

from adaptdiffuser.intervals import ONE_SEED

REPO = Path(__file__).resolve().parents[1]

#: each document and the section that holds its re-test table(s)
SECTIONS = {
    "README.md": "## Does self-evolution help?",
    "docs/results.md": "## Maze2D Large re-tested on start states no one tuned on",
}

MARKER = re.compile(r"<!--\s*figures:(?P<sources>.*?)-->")
NUMBER = re.compile(r"[-+]?\d+(?:\.\d+)?")
TRIPLE = re.compile(r"([-+]?\d+\.\d+) \[([-+]?\d+\.\d+), ([-+]?\d+\.\d+)\]")
SEED = re.compile(r"/seed(\d+)/")

#: header substring -> column kind, first match wins (the first column is always the models')
KINDS = (
    ("per seed", "per_seed"),
    ("committed", "committed"),
    ("start states", "states"),
    ("interval over", "over"),
    ("win rate", "win_rate"),
    ("control", "control"),
    ("gain", "gain"),
    ("score", "score"),
)

Expected = list[tuple[float, int]]  # (value, decimals as printed)


@cache
def load(path: str) -> dict:
    return json.loads((REPO / path).read_text())


@dataclass
class Table:
    sources: dict[str, str]
    header: list[str]
    rows: list[list[str]]
    line: int  # 1-based line of the marker


def cells(line: str) -> list[str]:
    return [c.strip() for c in line.strip().strip("|").split("|")]


def section(text: str, heading: str) -> str:
    """The text from ``heading`` to the next heading of its level (or the end)."""
    start = text.index(heading + "\n")
    level = heading.split(" ", 1)[0]
    nxt = re.search(rf"^{level} ", text[start + len(heading) :], flags=re.M)
    return text[start : start + len(heading) + nxt.start()] if nxt else text[start:]


def table_below(lines: list[str], i: int) -> list[str]:
    """The table rows right below line ``i``."""
    body = []
    for row in lines[i + 1 :]:
        if not row.startswith("|"):
            break
        body.append(row)
    return body


def marked_tables(text: str, first_line: int = 1) -> list[Table]:
    lines = text.splitlines()
    tables = []
    for i, line in enumerate(lines):
        m = MARKER.fullmatch(line.strip())
        if not m:
            continue
        sources = dict(token.split("=", 1) for token in m["sources"].split())
        body = table_below(lines, i)
        assert len(body) >= 3, f"line {i + 1}: a figures marker must sit right above a table"
        assert set(body[1]) <= set("|-: "), f"line {i + 2}: no separator row under the header"
        tables.append(Table(sources, cells(body[0]), [cells(r) for r in body[2:]], first_line + i))
    return tables


def column_kind(index: int, header: str) -> str:
    if index == 0:
        return "models"
    for key, kind in KINDS:
        if key in header.lower():
            return kind
    raise AssertionError(f"column {header!r}: no rule checks it")


def rounded(value: float, decimals: int) -> float:
    return float(f"{value:.{decimals}f}")


def printed(cell: str) -> list[tuple[float, int]]:
    return [(float(t), len(t.split(".")[1]) if "." in t else 0) for t in NUMBER.findall(cell)]


def shows(cell: str, want: Expected) -> bool:
    """Whether ``cell`` prints exactly the numbers ``want``, in order, each rounded as printed."""
    got = printed(cell)
    return len(got) == len(want) and all(
        d == dw and v == rounded(w, dw) for (v, d), (w, dw) in zip(got, want, strict=True)
    )


def interval(block: dict, what: str) -> Expected:
    iv = block["interval"][what]
    return [(iv["mean"], 1), (iv["ci_low"], 1), (iv["ci_high"], 1)]


def expected_cell(kind: str, cell: str, recipe: str, held_out: bool, sources: dict[str, str]) -> Expected:
    data = load(sources[recipe])
    block = data["held_out"] if held_out else data
    names = list(block["models"])
    seeds = [int(SEED.search(name).group(1)) for name in names]
    if kind == "models":
        return [(s, 0) for s in seeds]
    if kind == "states":
        bases = {block["eval_seeds"][name] - s for name, s in zip(names, seeds, strict=True)}
        assert len(bases) == 1, f"{sources[recipe]}: the seeds' start states have no common base"
        return [(bases.pop(), 0)]
    if kind == "over":
        overs = {block["interval"][what]["over"] for what in ("score", "control", "gain")}
        assert len(overs) == 1
        over = overs.pop()
        if over == "episodes":
            assert ONE_SEED in cell, f"a one-seed interval must read {ONE_SEED!r}: {cell!r}"
            return []
        assert over == "seeds" and "seeds" in cell, cell
        return [(block["interval"]["gain"]["n_seeds"], 0)]
    if kind in ("score", "control", "gain"):
        iv = block["interval"][kind]
        if kind == "gain":
            excludes_zero = iv["ci_low"] > 0 or iv["ci_high"] < 0
            assert ("**" in cell) == excludes_zero, f"bold exactly when the interval excludes zero: {cell!r}"
        return interval(block, kind)
    if kind == "win_rate":
        return [(block["interval"]["gain"]["win_rate"], 2)]
    if kind == "per_seed":
        out: Expected = []
        for name, s in zip(names, seeds, strict=True):
            m = block["models"][name]
            out += [(s, 0), (m["model"]["score_mean"], 1), (m["control"]["score_mean"], 1)]
            out += [(m["gain"]["gain_mean"], 1), (m["gain"]["gain_stderr"], 1)]
        return out
    if kind == "committed":
        if held_out:  # the science runs played no held-out set
            return []
        task = SEED.split(names[0])[0]
        phase = load(sources[f"committed-{recipe}"])[task]["phase_1"]
        per_seed = phase["per_seed"]
        if len(seeds) == 1:
            one = per_seed[str(seeds[0])]
            return [(one["gain_mean"], 1), (one["gain_stderr"], 1)]
        assert sorted(per_seed) == sorted(map(str, seeds)) and phase["n_seeds"] == len(seeds)
        each = [(per_seed[str(s)]["gain_mean"], 1) for s in seeds]
        return [(phase["gain_mean"], 1), (phase["gain_stderr"], 1), *each]
    raise AssertionError(kind)


def check_table(table: Table) -> list[str]:
    errors = []
    try:
        kinds = [column_kind(i, h) for i, h in enumerate(table.header)]
    except AssertionError as e:
        return [f"table at line {table.line}: {e}"]
    if "states" not in kinds:
        return [f"table at line {table.line}: no start-states column"]
    recipes = [k for k in table.sources if not k.startswith(("committed-", "record-"))]
    seen = []
    for r, row in enumerate(table.rows):
        where = f"table at line {table.line}, row {r + 1}"
        if len(row) != len(kinds):
            errors.append(f"{where}: {len(row)} cells for {len(kinds)} columns")
            continue
        named = [w for w in re.findall(r"`([^`]+)`", row[0]) if w in recipes]
        states = row[kinds.index("states")]
        if not named or ("own" in states) == ("held out" in states):
            errors.append(f"{where}: cannot tell its JSON ({recipes}) or its start states (own / held out)")
            continue
        recipe, held_out = named[0], "held out" in states
        seen.append((recipe, held_out))
        for kind, header, cell in zip(kinds, table.header, row, strict=True):
            try:
                want = expected_cell(kind, cell, recipe, held_out, table.sources)
            except AssertionError as e:
                errors.append(f"{where}, {header!r}: {e}")
                continue
            if not shows(cell, want):
                shown = ", ".join(f"{w:.{d}f}" for w, d in want)
                source = table.sources[f"committed-{recipe}" if kind == "committed" else recipe]
                errors.append(f"{where}, {header!r}: {cell!r} is not [{shown}] ({source})")
    wanted = [(recipe, held_out) for recipe in recipes for held_out in (False, True)]
    if sorted(seen) != sorted(wanted):
        errors.append(f"table at line {table.line}: rows {seen}, want each of {wanted} once")
    return errors


def allowed_triples(sources: dict[str, str]) -> set[tuple[float, float, float]]:
    out = set()
    for key, path in sources.items():
        if key.startswith("committed-"):
            continue
        if key.startswith("record-"):  # a pipeline record: one task's science summary
            (record,) = load(path).values()
            phases = [v for k, v in record.items() if k.startswith("phase_")]
            entries = [e for phase in phases for e in (phase, phase.get("control")) if e]
            blocks = [b for e in entries for b in (e, e.get("held_out")) if b]
            for block, name in ((b, n) for b in blocks for n in ("score", "gain") if f"{n}_ci_low" in b):
                out.add(tuple(rounded(value, 1) for value, _ in triple(block, name)))
            continue
        data = load(path)
        for block in (data, data["held_out"]):
            for iv in block["interval"].values():
                for lo, hi in (("ci_low", "ci_high"), ("episode_ci_low", "episode_ci_high")):
                    out.add((rounded(iv["mean"], 1), rounded(iv[lo], 1), rounded(iv[hi], 1)))
    return out


def check(text: str, heading: str) -> list[str]:
    """Every problem with the marked tables, and with the prose's intervals, of ``heading``'s section."""
    part = section(text, heading)
    tables = marked_tables(part, first_line=text[: text.index(part)].count("\n") + 1)
    if not tables:
        return [f"{heading!r}: no table marked <!-- figures: ... -->"]
    errors = [e for table in tables for e in check_table(table)]
    allowed = set().union(*(allowed_triples(t.sources) for t in tables))
    prose = " ".join(line for line in part.splitlines() if not line.startswith("|"))  # an interval may wrap
    for m in TRIPLE.finditer(prose):
        parts = m.groups()
        if any(len(p.split(".")[1]) != 1 for p in parts) or tuple(map(float, parts)) not in allowed:
            errors.append(f"{heading!r}: {m[0]!r} in the prose is no interval of the named JSONs")
    return errors


@pytest.mark.parametrize("doc", list(SECTIONS))
def test_every_retest_figure_is_its_committed_json(doc: str) -> None:
    assert check((REPO / doc).read_text(), SECTIONS[doc]) == []


@pytest.mark.parametrize("doc", list(SECTIONS))
def test_the_named_files_are_committed(doc: str) -> None:
    """Not only present here: tracked by git, so that a clone can check them."""
    listed = subprocess.run(["git", "ls-files"], cwd=REPO, check=True, capture_output=True, text=True).stdout
    tracked = set(listed.split())
    for table in marked_tables(section((REPO / doc).read_text(), SECTIONS[doc])):
        assert set(table.sources.values()) <= tracked, table.sources


def table_numbers(text: str, heading: str) -> list[re.Match]:
    """Every number in the body rows of the section's marked tables, as matches in ``text``."""
    start = text.index(heading + "\n")
    part = section(text, heading)
    lines = part.splitlines(keepends=True)
    out, offset, in_table, row = [], start, False, 0
    for line in lines:
        if MARKER.fullmatch(line.strip()):
            in_table, row = True, 0
        elif in_table and line.startswith("|"):
            row += 1
            if row >= 3:  # past the header and the separator
                out += [m for m in NUMBER.finditer(text, offset, offset + len(line))]
        else:
            in_table = False
        offset += len(line)
    return out


@pytest.mark.parametrize("doc", list(SECTIONS))
def test_a_changed_number_in_any_cell_fails(doc: str) -> None:
    text = (REPO / doc).read_text()
    heading = SECTIONS[doc]
    numbers = table_numbers(text, heading)
    assert len(numbers) >= 40
    for m in numbers:
        last = m.end() - 1
        tampered = text[:last] + str((int(text[last]) + 1) % 10) + text[last + 1 :]
        assert check(tampered, heading), f"changing {m[0]!r} at offset {m.start()} went unnoticed"


def test_other_tampering_fails() -> None:
    text = (REPO / "README.md").read_text()
    heading = SECTIONS["README.md"]
    row = next(line for line in text.splitlines() if line.startswith("| `plans`, seeds 0, 1, 2, 3, 4 | held out"))

    def fails(old: str, new: str, count: int = 1) -> None:
        assert text.count(old) >= 1, old
        assert check(text.replace(old, new, count), heading), f"{old!r} -> {new!r} went unnoticed"

    fails(row + "\n", "")  # a row dropped
    fails("| 0.43 |", "| 0.43 (0.12) |")  # a number no JSON has, added
    fails("| 0.43 |", "| 0.4 |")  # the right number, rounded otherwise than printed
    fails("| 3 seeds (Student t) |", "| one seed: over episodes |")  # an interval over seeds labelled as one seed's
    fails("-3.5 [-10.8, 3.9]", "**-3.5 [-10.8, 3.9]**")  # bold that claims zero is excluded
    fails("-3.5 [-10.8, 3.9] on its own", "-3.5 [-7.2, -0.1] on its own")  # the superseded interval, in the prose
    fails("rollouts=metrics/science/maze2d-large-retest/rollouts.json", "")  # the JSON not named
    fails("<!-- figures:", "<!-- no figures:")  # the marker lost
    fails("+7.9 [0.3, 15.5]", "+7.9 [0.3, 15.6]")  # a pipeline record's interval, in the prose, changed
    fails(" record-large=metrics/science/maze2d-large.json", "")  # the record not named
    fails("| win rate |", "| win rate | note |")  # a column no rule checks


def test_the_checker_reads_a_minimal_table() -> None:
    """The README's table, rebuilt from the JSONs, passes; so the checker is not just matching the file to itself."""
    retest = "metrics/science/maze2d-large-retest"
    lines = [
        "## Re-test",
        "",
        f"<!-- figures: plans={retest}/plans-seed2.json -->",
        "| recipe | start states | interval over | gain [95 %] | win rate |",
        "|---|---|---|---|---|",
    ]
    data = load(f"{retest}/plans-seed2.json")
    for label, block, base in (("own", data, 3000), ("held out", data["held_out"], 7000)):
        g = block["interval"]["gain"]
        lines.append(
            f"| `plans`, seed 2 | {label}, {base} + s | {ONE_SEED} | "
            f"**{g['mean']:+.1f} [{g['ci_low']:.1f}, {g['ci_high']:.1f}]** | {g['win_rate']:.2f} |"
        )
    text = "\n".join(lines) + "\n\nGain +7.8 [4.3, 11.3] on its own states.\n"
    assert check(text, "## Re-test") == []
    assert check(text.replace("+7.8 [4.3, 11.3] on", "+7.8 [4.3, 11.4] on"), "## Re-test")


# -- pipeline records (science summaries) ------------------------------------------------------------------------------

SUMMARY_MARKER = re.compile(r"<!--\s*summary:\s*(?P<path>\S+)\s+per-seed=(?P<per_seed>\S+)\s*-->")

#: header substring -> column kind of a pipeline record's table, first match wins
SUMMARY_KINDS = (
    ("per-seed", "per_seed"),
    ("start states", "states"),
    ("gain", "gain"),
    ("control", "control"),
    ("win rate", "win_rate"),
    ("success", "success"),
    ("score", "score"),
    ("phase", "phase"),
)


def triple(block: dict, name: str) -> Expected:
    return [(block[f"{name}_mean"], 1), (block[f"{name}_ci_low"], 1), (block[f"{name}_ci_high"], 1)]


def summary_cell(kind: str, cell: str, record: dict, per_seed: Path, phase: int, held_out: bool) -> Expected:
    assert f"phase_{phase}" in record, f"the record has no phase {phase}"
    entry = record[f"phase_{phase}"]
    block = entry["held_out"] if held_out else entry
    if kind == "phase":
        return [(phase, 0)]
    if kind == "states":
        return []
    if kind == "score":
        return triple(block, "score")
    if kind == "success":
        return [(block["success_rate"], 2)]
    if phase == 0:  # no control, gain or win rate
        return []
    control = entry["control"]["held_out"] if held_out else entry["control"]
    if kind == "control":
        return [*triple(control, "score"), (control["success_rate"], 2)]
    if kind == "gain":
        excludes_zero = block["gain_ci_low"] > 0 or block["gain_ci_high"] < 0
        assert ("**" in cell) == excludes_zero, f"bold exactly when the interval excludes zero: {cell!r}"
        return triple(block, "gain")
    if kind == "win_rate":
        return [(block["win_rate"], 2)]
    if kind == "per_seed":
        seeds = json.loads((per_seed / f"phase{phase}-control.json").read_text())["seeds"]
        return [((seeds[s]["held_out"] if held_out else seeds[s])["gain_mean"], 1) for s in sorted(seeds, key=int)]
    raise AssertionError(kind)


def check_summary_tables(text: str) -> list[str]:
    """Every problem with the tables of ``text`` marked ``<!-- summary: ... -->``."""
    lines, errors = text.splitlines(), []
    for i, line in enumerate(lines):
        m = SUMMARY_MARKER.fullmatch(line.strip())
        if not m:
            continue
        (task, record), *more = json.loads((REPO / m["path"]).read_text()).items()
        assert not more, f"line {i + 1}: {m['path']} holds more than one task"
        body = table_below(lines, i)
        header = cells(body[0])
        kinds = [next(kind for key, kind in SUMMARY_KINDS if key in h.lower()) for h in header]
        seen = []
        for r, row in enumerate(cells(b) for b in body[2:]):
            where = f"table at line {i + 1}, row {r + 1}"
            states = row[kinds.index("states")]
            phase, held_out = int(NUMBER.findall(row[kinds.index("phase")])[0]), "held out" in states
            if ("own" in states) == held_out:
                errors.append(f"{where}: cannot tell its start states (own / held out)")
                continue
            seen.append((phase, held_out))
            for kind, head, cell in zip(kinds, header, row, strict=True):
                try:
                    want = summary_cell(kind, cell, record, REPO / m["per_seed"], phase, held_out)
                except AssertionError as e:
                    errors.append(f"{where}, {head!r}: {e}")
                    continue
                if not shows(cell, want):
                    shown = ", ".join(f"{w:.{d}f}" for w, d in want)
                    errors.append(f"{where}, {head!r}: {cell!r} is not [{shown}] ({m['path']}, {task})")
        phases = sorted(int(k.split("_")[1]) for k in record if k.startswith("phase_"))
        if sorted(seen) != [(ph, h) for ph in phases for h in (False, True)]:
            errors.append(f"table at line {i + 1}: rows {seen}, want each phase of {phases} on both sets once")
    return errors


def test_every_pipeline_record_figure_is_its_committed_summary() -> None:
    text = (REPO / "docs/results.md").read_text()
    assert SUMMARY_MARKER.search(text), "docs/results.md: no table marked <!-- summary: ... -->"
    assert check_summary_tables(text) == []


def test_a_changed_number_or_row_in_a_pipeline_record_table_fails() -> None:
    text = (REPO / "docs/results.md").read_text()
    lines = text.splitlines(keepends=True)
    markers = [i for i, line in enumerate(lines) if SUMMARY_MARKER.fullmatch(line.strip())]
    bolds = 0
    for marker in markers:
        rows = table_below([line.rstrip("\n") for line in lines], marker)[2:]
        offset = sum(len(line) for line in lines[: marker + 3])  # the first body row's start
        body = "".join(lines[marker + 3 : marker + 3 + len(rows)])
        numbers = list(NUMBER.finditer(body))
        assert len(numbers) >= 20
        for m in numbers:
            last = offset + m.end() - 1
            tampered = text[:last] + str((int(text[last]) + 1) % 10) + text[last + 1 :]
            assert check_summary_tables(tampered), f"changing {m[0]!r} went unnoticed"
        assert check_summary_tables(text.replace(rows[-1] + "\n", "", 1)), "a dropped row went unnoticed"
        for bold in (row for row in rows if "**" in row):
            bolds += 1
            assert check_summary_tables(text.replace(bold, bold.replace("**", ""), 1)), "bold lost, unnoticed"
    assert bolds, "no bold gain in any pipeline record table: the bold rule goes untested"
