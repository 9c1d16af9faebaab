"""The documentation's code blocks stay true to the code: every `reachwatch ...` line of
a shell block in README.md and docs/ parses with the real argument parser, the files
and scripts the blocks name exist, the guides' Python blocks marked runnable run as
pasted, and README's links into the repository resolve."""

import contextlib
import io
import re
import shlex
from pathlib import Path

import pytest

from reachwatch.pipeline.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md"] + sorted((ROOT / "docs").rglob("*.md"))
GUIDES = sorted((ROOT / "docs" / "guides").glob("*.md"))
FENCE = re.compile(r"^```(\w*)\n(.*?)^```", re.S | re.M)


def shell_lines(path):
    """The command lines of a page's ```sh / ```bash blocks (and ``$ `` lines of plain
    blocks): continuations joined, comments and prompts dropped."""
    lines = []
    for lang, body in FENCE.findall(path.read_text()):
        if lang not in ("sh", "bash", "shell", ""):
            continue
        body = body.replace("\\\n", " ")
        for line in body.splitlines():
            if lang == "":
                if not line.startswith("$ "):
                    continue
            line = line.removeprefix("$ ").strip()
            line = re.sub(r"\s+#.*$", "", line)
            if line and not line.startswith("#"):
                lines.append(line)
    return lines


def all_commands():
    return [(path.relative_to(ROOT).as_posix(), line)
            for path in PAGES for line in shell_lines(path)]


def test_pages_have_commands():
    commands = [line for _, line in all_commands()]
    assert sum(line.startswith("reachwatch ") for line in commands) >= 8
    assert any(line.startswith("make ") for line in commands)


@pytest.mark.parametrize("page, line", [c for c in all_commands()
                                        if c[1].startswith("reachwatch ")])
def test_reachwatch_command_lines_parse(page, line):
    argv = shlex.split(line)[1:]
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            args = build_parser().parse_args(argv)
    except SystemExit as e:
        pytest.fail(f"{page}: `{line}` does not parse (exit {e.code}): {err.getvalue()}")
    for name in ("scenario",):
        value = getattr(args, name, None)
        if value and value.startswith(("scenarios/", "examples/")):
            assert (ROOT / value).is_file(), f"{page}: `{line}` names a missing file {value}"


@pytest.mark.parametrize("page, line", [c for c in all_commands()
                                        if c[1].startswith(("python ", "make "))])
def test_scripts_and_make_targets_exist(page, line):
    words = shlex.split(line)
    if words[0] == "make":
        targets = re.findall(r"^([\w-]+):", (ROOT / "Makefile").read_text(), re.M)
        assert words[1] in targets, f"{page}: `{line}`: no such make target"
    elif words[1] != "-m":
        assert (ROOT / words[1]).is_file(), f"{page}: `{line}`: no script {words[1]}"


def runnable_blocks(path):
    """The ```python blocks right after a ``<!-- runnable -->`` line."""
    return re.findall(r"<!-- runnable -->\n```python\n(.*?)```", path.read_text(), re.S)


@pytest.mark.parametrize("guide", [g for g in GUIDES if runnable_blocks(g)],
                         ids=lambda g: g.name)
def test_runnable_guide_blocks_run_as_pasted(guide, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    namespace = {"__name__": f"guide_{guide.stem}"}
    for block in runnable_blocks(guide):
        saved = re.fullmatch(r"#\s*([\w./-]+\.py)", block.splitlines()[0].strip())
        if saved:                           # a file the reader saves, e.g. my_controller.py
            (tmp_path / saved.group(1)).write_text(block)
        else:
            exec(compile(block, f"<{guide.name}>", "exec"), namespace)


def test_guides_with_code_mark_it_runnable():
    marked = {g.name for g in GUIDES if runnable_blocks(g)}
    assert {"own-controller.md", "own-plant.md"} <= marked


def test_readme_links_resolve():
    text = (ROOT / "README.md").read_text()
    for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text):
        if "://" in target:
            continue
        assert (ROOT / target).exists(), f"README.md links to a missing {target}"


def run_file_fragments(path):
    """``(run file, fragment)`` of each ```yaml block right after a
    ``<!-- appended to RUNFILE -->`` line."""
    return re.findall(r"<!-- appended to ([\w./-]+) -->\n```yaml\n(.*?)```", path.read_text(),
                      re.S)


@pytest.mark.parametrize("page, run_file, fragment",
                         [(g.name, f, b) for g in GUIDES for f, b in run_file_fragments(g)])
def test_run_file_fragments_validate_appended_to_their_run_file(page, run_file, fragment):
    from reachwatch.pipeline.spec import load_run_spec
    text = (ROOT / run_file).read_text() + "\n" + fragment
    spec = load_run_spec(data=text)               # validates: refused in one line if not
    import yaml
    for key, value in yaml.safe_load(fragment).items():      # the fragment's keys took
        for field, given in (value.items() if isinstance(value, dict) else [(None, value)]):
            got = getattr(spec, key) if field is None else getattr(getattr(spec, key), field)
            if not isinstance(given, dict):
                assert got == given, f"{page}: {key}.{field} is {got!r}, the guide gives {given!r}"


def test_guides_show_a_run_file_fragment():
    assert any(run_file_fragments(g) for g in GUIDES)
