"""The manual tells the truth: README.md is short, every `cosy` command and option that README.md
and docs/*.md name exists, the README's demo block is what `make demo` runs, the pages it links
exist, and no file of the repository names a folder of one particular machine."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import click
import pytest

from cosy_cli.cli.main import cli

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"
DOCS = sorted((REPO / "docs").glob("*.md"))
README_MAX_LINES = 300


# --- reading Markdown -------------------------------------------------------------------------

FENCE = re.compile(r"^\s*(```|~~~)")


def code_blocks(text: str) -> list[tuple[int, str]]:
    """(line number of the opening fence, body) of every fenced code block."""
    blocks, body, start, fence = [], [], 0, None
    for i, line in enumerate(text.split("\n"), 1):
        m = FENCE.match(line)
        if fence is None and m:
            fence, start, body = m.group(1), i, []
        elif fence is not None and line.strip().startswith(fence):
            blocks.append((start, "\n".join(body)))
            fence = None
        elif fence is not None:
            body.append(line)
    return blocks


def inline_spans(text: str) -> list[tuple[int, str]]:
    """(line number, content) of every inline code span outside fenced blocks (spans may wrap
    onto the next line, as in a paragraph)."""
    prose, fence = [], None
    for line in text.split("\n"):
        m = FENCE.match(line)
        if fence is None and m:
            fence = m.group(1)
            prose.append("")
        elif fence is not None:
            if line.strip().startswith(fence):
                fence = None
            prose.append("")
        else:
            prose.append(line)
    joined = "\n".join(prose)
    spans = []
    for m in re.finditer(r"(`+)(.+?)\1", joined, flags=re.S):
        spans.append((joined.count("\n", 0, m.start()) + 1, m.group(2).replace("\n", " ")))
    return spans


def command_lines(block: str) -> list[str]:
    """The block's commands: continuation lines joined, comments dropped, split at ; && and ' | '."""
    out = []
    for line in block.replace("\\\n", " ").split("\n"):
        line = re.sub(r"(^|\s)#.*$", "", line).strip()
        out += [part.strip() for part in re.split(r";|&&|\s\|\s", line) if part.strip()]
    return out


# --- checking against the click group ---------------------------------------------------------

def _options(cmd: click.Command) -> set[str]:
    names = {"--help", "-h"}
    for p in cmd.params:
        if isinstance(p, click.Option):
            names.update(p.opts)
            names.update(p.secondary_opts)
    return names


def _kind_choices(cmd: click.Command) -> set[str] | None:
    """Choices of a command's first positional argument (`cosy train KIND`), if it has one."""
    for p in cmd.params:
        if isinstance(p, click.Argument) and isinstance(p.type, click.Choice):
            return set(p.type.choices)
    return None


ALL_OPTIONS = set().union(*(_options(c) for c in cli.commands.values()))
OPTION = re.compile(r"^--?[A-Za-z][\w-]*$")
PLACEHOLDER = re.compile(r"^[A-Z][A-Z0-9_]*$|^\.\.\.?$|^…$")


def _option_names(token: str) -> list[str]:
    """'--a=1' -> ['--a']; '[--coarse/--refiner]' -> ['--coarse', '--refiner']; else []."""
    token = token.strip("[](),;.:'\"")
    names = []
    for part in token.split("/"):
        part = part.split("=", 1)[0]
        if OPTION.match(part):
            names.append(part)
    return names


def check_segment(words: list[str], where: str) -> list[str]:
    """Problems of one command line ``words`` (starting after the word ``cosy``)."""
    if not words:
        return []
    name = words[0].strip("[](),;.:'\"`")
    if not name or PLACEHOLDER.match(name) or name.startswith("-"):  # `cosy COMMAND --help`, `cosy --version`
        return []
    cmd = cli.commands.get(name)
    if cmd is None:
        return [f"{where}: `cosy {name}` is no cosy command"]
    problems = []
    rest = words[1:]
    choices = _kind_choices(cmd)
    if choices is not None and rest and not rest[0].startswith("-"):
        kind = rest[0].strip("[](),;.:'\"")
        if kind and not PLACEHOLDER.match(kind) and kind not in choices:
            problems.append(f"{where}: `cosy {name} {kind}`: {kind} is not one of {sorted(choices)}")
    known = _options(cmd)
    for token in rest:
        for opt in _option_names(token):
            if opt not in known:
                problems.append(f"{where}: `cosy {name}` has no option {opt}")
    return problems


def _is_cosy(word: str) -> bool:
    word = word.strip("[(`'\"")
    return word == "cosy" or word.endswith("/cosy") or word == "$(COSY)"


def check_text(text: str, source: str) -> list[str]:
    """Every `cosy COMMAND [KIND] --option` in the code blocks and inline code of ``text``: the
    command must exist, the kind be one of its choices, and the option be one of its options; an
    inline span that is only options (`--top-k 12`) needs each option on some cosy command."""
    problems = []
    segments = []
    for line_no, block in code_blocks(text):
        segments += [(line_no, cmd) for cmd in command_lines(block)]
    segments += inline_spans(text)
    for line_no, segment in segments:
        where = f"{source}:{line_no}"
        words = segment.split()
        starts = [i for i, w in enumerate(words) if _is_cosy(w)]
        if starts:
            for a, b in zip(starts, starts[1:] + [len(words)]):
                problems += check_segment(words[a + 1:b], where)
        elif words and words[0].startswith("-"):
            for token in words:
                for opt in _option_names(token):
                    if opt not in ALL_OPTIONS:
                        problems.append(f"{where}: no cosy command has the option {opt}")
    return problems


def test_readme_is_a_short_manual():
    n = len(README.read_text().split("\n"))
    assert n <= README_MAX_LINES, f"README.md has {n} lines; at most {README_MAX_LINES}: move details to docs/"
    assert DOCS, "docs/*.md missing"


@pytest.mark.parametrize("path", [README] + DOCS, ids=lambda p: p.name)
def test_every_command_and_option_named_exists(path):
    problems = check_text(path.read_text(), path.relative_to(REPO).as_posix())
    assert not problems, "\n".join(problems)


def test_the_checker_catches_misspelt_commands_options_and_kinds():
    bad = """
Run `cosy estimate --verfy-top 64` or `--top-kk 3`, then `cosy mach --dataset d`.

```bash
cosy refine --dataset d --matches m --out r \\
    --loss-treshold-px 25
cosy train refinr --dataset d --out r
make demo && cosy evaluate --dataset d --predictions p.csv --out e --no-vds
```
"""
    problems = "\n".join(check_text(bad, "bad.md"))
    for wrong in ("--verfy-top", "--top-kk", "cosy mach", "--loss-treshold-px", "refinr", "--no-vds"):
        assert wrong in problems, f"the checker missed {wrong}:\n{problems}"
    good = """
`cosy estimate --verify-top 64 [--top-k 12]`, `--icp-screen 32`, `cosy match --no-refit`,
`cosy COMMAND --help`, `cosy train scorer --models m --out s.onnx`, `cosy run ... --set a.b=1`.

```bash
cosy refine --dataset d --matches m --out r \\
    --loss-threshold-px 25   # a comment --not-an-option
.venv/bin/cosy evaluate --dataset d --predictions p.csv --out e --no-vsd
python benchmarks/bench_x.py --anything
```
"""
    assert check_text(good, "good.md") == []


# --- the demo block is what `make demo` runs --------------------------------------------------

def _split_args(s: str) -> list[str]:
    """Top-level comma-separated arguments of a Make function call body."""
    args, depth, cur = [], 0, ""
    for ch in s:
        if ch == "," and depth == 0:
            args.append(cur)
            cur = ""
            continue
        depth += ch == "("
        depth -= ch == ")"
        cur += ch
    return args + [cur]


def make_expand(s: str, variables: dict[str, str]) -> str:
    """Expands $(VAR), $(wildcard PATH) and $(if COND,THEN,ELSE) as make would, enough for the
    Makefile's demo recipe."""
    out, i = "", 0
    while i < len(s):
        if s.startswith("$(", i):
            depth, j = 1, i + 2
            while depth:
                depth += {"(": 1, ")": -1}.get(s[j], 0)
                j += 1
            body = s[i + 2:j - 1]
            if body.startswith("if "):
                cond, then, *other = _split_args(body[3:])
                chosen = then if make_expand(cond, variables).strip() else (other[0] if other else "")
                out += make_expand(chosen, variables)
            elif body.startswith("wildcard "):
                path = make_expand(body[len("wildcard "):], variables).strip()
                out += path if (REPO / path).exists() else ""
            else:
                out += make_expand(variables.get(body, ""), variables)
            i = j
        elif s.startswith("$$", i):
            out, i = out + "$", i + 2
        else:
            out, i = out + s[i], i + 1
    return out


def makefile_demo_commands() -> list[str]:
    text = (REPO / "Makefile").read_text().replace("\\\n", " ")
    variables = {}
    for m in re.finditer(r"^([A-Z_]+)\s*(?::=|\?=|=)\s*(.*)$", text, flags=re.M):
        variables.setdefault(m.group(1), m.group(2).strip())
    variables["COSY"] = "cosy"
    lines = text.split("\n")
    start = next(i for i, line in enumerate(lines) if re.match(r"^demo\s*:", line))
    recipe = []
    for line in lines[start + 1:]:
        if not line.startswith("\t"):
            break
        recipe.append(line.strip().lstrip("@-"))
    commands = [" ".join(make_expand(line, variables).split()) for line in recipe]
    return [c for c in commands if c]


def readme_demo_commands() -> list[str]:
    text = README.read_text()
    marker = "<!-- make demo -->"
    assert text.count(marker) == 1, f"README.md needs exactly one {marker} before the demo's code block"
    after = text.split(marker, 1)[1]
    blocks = code_blocks(after)
    assert blocks and blocks[0][0] <= 2, f"the code block must follow {marker} directly"
    return [" ".join(c.split()) for c in command_lines(blocks[0][1])]


def test_makefile_demo_is_parsed():
    commands = makefile_demo_commands()
    assert commands and all(c.startswith("cosy ") for c in commands), commands
    assert any(c.startswith("cosy run ") for c in commands)


def test_readme_demo_block_is_what_make_demo_runs():
    assert readme_demo_commands() == makefile_demo_commands()


def test_make_expand():
    v = {"A": "x", "B": "$(A)y", "E": ""}
    assert make_expand("$(B) $(if $(A),yes $(A),no) $(if $(E),yes,no $(B))", v) == "xy yes x no xy"
    assert make_expand("$(wildcard no/such/file)", v) == ""


# --- links and machine paths ------------------------------------------------------------------

@pytest.mark.parametrize("path", [README, REPO / "CONTRIBUTING.md"] + DOCS, ids=lambda p: p.name)
def test_relative_links_point_at_files(path):
    text = path.read_text()
    missing = []
    for target in re.findall(r"\]\(([^)\s]+)\)", text):
        if re.match(r"^[a-z]+:", target) or target.startswith("#"):
            continue
        if not (path.parent / target.split("#", 1)[0]).exists():
            missing.append(target)
    assert not missing, f"{path.name}: links to missing files: {missing}"


# An absolute folder of one particular computer: a home, work, temporary or user folder at the root
# of a file system, or a Windows user folder (not preceded by a word character, a dot, a tilde or a slash, so relative paths such as
# runs/tmp/x, ~/.cache or ../shared are fine).
MACHINE_PATH = re.compile(r"(?<![\w.~/$-])/(?:work|home|tmp|root|opt|mnt|Users|scratch)/"
                          r"|\b[A-Z]:\\(?:Users|Documents and Settings)\\")
# .gitignore's patterns are anchored at the repository root (its tmp entry is the repository's own tmp).
NOT_SCANNED = {".gitignore"}


def machine_paths(text: str) -> list[str]:
    return [line.strip() for line in text.split("\n") if MACHINE_PATH.search(line)]


def test_machine_path_pattern():
    # (the examples are assembled so that this file does not contain what it looks for)
    root = "/"
    assert machine_paths(f'default=Path("{root}tmp/cosy_heldout")')
    assert machine_paths(f"see {root}work/main/README")
    assert machine_paths(f"cp x {root}home/someone/data")
    assert machine_paths("C:" + "\\Users\\someone\\data")
    assert not machine_paths("runs/tmp/x ~/.cache/cosy ../shared/realdata tempfile.gettempdir()")
    assert not machine_paths("$(DEMO_OUT)/templates and src/cosy_cli/opt/x")


def test_no_machine_paths_in_the_repository():
    try:
        files = subprocess.run(["git", "ls-files", "-z"], cwd=REPO, capture_output=True, check=True,
                               text=True).stdout.split("\0")
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("not a git checkout")
    found = []
    for name in files:
        if not name or name in NOT_SCANNED or not (REPO / name).is_file():
            continue
        data = (REPO / name).read_bytes()
        if b"\0" in data[:8192]:
            continue  # binary
        for line in machine_paths(data.decode("utf-8", errors="replace")):
            found.append(f"{name}: {line[:120]}")
    assert not found, "absolute folders of one machine (use an argument or ../shared/...):\n" + "\n".join(found)
