"""The documentation against the code.

- docs/parameters.md is the page `mireg param-docs` generates from the declared parameters.
- Every command of the README's ```sh blocks works as written on a fresh clone, as far as that
  is cheap to know: `mireg` lines are parsed by mireg's own parser (every flag and argument
  must exist) and each command's --help runs; the node's command lines name real parameters
  with acceptable values and files that exist; the launch file declares every argument given;
  a `make` target exists (running `make demo` is left to the demo's own test); a command the
  README wraps in `$(...)` runs. A command this test does not know fails it, so a new kind
  of line in the README needs a check here too.
"""
from __future__ import annotations

import ast
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
# Top-level folders of the repository: a README token starting with one of them is a path
# into the clone, which must exist (other paths are the user's own files).
REPO_DIRS = ("config/", "launch/", "docs/", "multi_instance_reg/", "interfaces/", "test/")


def readme_commands(text: str) -> list[str]:
    """The command lines of the ```sh blocks: continuations joined, comments and blanks dropped."""
    commands = []
    for block in re.findall(r"^```sh\n(.*?)^```", text, re.S | re.M):
        for line in block.replace("\\\n", " ").splitlines():
            if line.strip() and not line.lstrip().startswith("#"):
                commands.append(line.strip())
    return commands


COMMANDS = readme_commands(README.read_text())


def test_the_readme_shows_commands():
    assert "make demo" in COMMANDS and "make test" in COMMANDS
    assert len(COMMANDS) >= 5


def test_the_pictures_the_readme_shows_exist():
    for target in re.findall(r"!\[[^\]]*\]\(([^)]+)\)", README.read_text()):
        assert (ROOT / target).is_file(), f"the README shows {target}, which is not in the repository"


def test_parameters_page_is_the_generated_one():
    from multi_instance_reg.tools.param_docs import parameters_markdown

    assert (ROOT / "docs" / "parameters.md").read_text() == parameters_markdown(), \
        "regenerate: mireg param-docs -o docs/parameters.md"


def _check_repo_paths(words: list[str]) -> None:
    for word in words:
        value = word.split(":=", 1)[-1].strip("'\"[],")
        if value.startswith(REPO_DIRS):
            assert (ROOT / value).exists(), f"the README names {value}, which is not in the repository"


def _make_targets() -> set[str]:
    return set(re.findall(r"^([\w-]+):", (ROOT / "Makefile").read_text(), re.M))


def _check_make(words: list[str]) -> None:
    missing = set(words[1:]) - _make_targets()
    assert not missing, f"the README runs make {' '.join(words[1:])}: no target {sorted(missing)} in the Makefile"


def _check_mireg(words: list[str]) -> None:
    from multi_instance_reg.tools.cli import parser_for

    argv = words[1:]
    try:
        parser_for(argv).parse_args(argv)
    except SystemExit as exc:
        pytest.fail(f"mireg refuses the README's command line ({exc}): {' '.join(words)}")
    _check_repo_paths(argv)


def _launch_arguments(path: Path) -> set[str]:
    """Names the launch file declares: the keys of its {name: (default, description)} table."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Dict) and node.values and all(
                isinstance(v, ast.Tuple) and len(v.elts) == 2 for v in node.values):
            names |= {k.value for k in node.keys if isinstance(k, ast.Constant)}
    return names


def _check_ros_arguments(words: list[str]) -> None:
    """--ros-args of the node: real parameters with acceptable values, files that exist."""
    from multi_instance_reg.params import read_params_yaml
    from multi_instance_reg.ros.parameters import all_specs

    specs = {s.name: s for s in all_specs()}
    rest = words[words.index("--ros-args") + 1:]
    while rest:
        flag, value, rest = rest[0], rest[1], rest[2:]
        if flag == "--params-file":
            assert (ROOT / value).is_file(), f"the README's parameter file {value} does not exist"
            assert set(read_params_yaml(ROOT / value)) <= set(specs)
        elif flag == "-p":
            name, _, text = value.partition(":=")
            assert name in specs, f"the README sets -p {name}, which the node does not declare"
            specs[name].check(yaml.safe_load(text))   # raises InputError on a bad value
        elif flag != "-r":
            pytest.fail(f"unknown ROS argument {flag} in the README: {' '.join(words)}")


def _check_node(words: list[str]) -> None:
    setup = (ROOT / "setup.py").read_text()
    assert f"{Path(words[0]).name} = " in setup, f"{words[0]} is not a console script of setup.py"
    _check_ros_arguments(words)


def _check_ros2(words: list[str]) -> None:
    verb, package = words[1], words[2]
    if package == "realsense2_camera":
        # The camera driver is not here to run; what matters is that it gives what the node
        # reads: depth aligned to colour.
        assert "align_depth.enable:=true" in words, "the RealSense line must align depth to colour"
        return
    assert package == "multi_instance_reg", f"the README runs another package: {' '.join(words)}"
    if verb == "launch":
        launch_file = ROOT / "launch" / words[3]
        assert launch_file.is_file(), f"no launch file launch/{words[3]}"
        declared = _launch_arguments(launch_file)
        from multi_instance_reg.ros.parameters import launch_model_parameters

        given = dict(w.split(":=", 1) for w in words[4:])
        assert set(given) <= declared, f"the launch file does not declare {sorted(set(given) - declared)}"
        launch_model_parameters(given.get("model_path", ""), given.get("model_paths", "").strip("'"))
    elif verb == "run":
        _check_node(words[3:])
    else:
        pytest.fail(f"ros2 {verb} is not checked here: {' '.join(words)}")


def _check_export(line: str) -> None:
    """export VAR=$(python -m ...): the inner command runs and names a file."""
    match = re.fullmatch(r"export \w+=\$\((python -m [\w.]+)\)", line)
    assert match, f"an export this test does not know: {line}"
    inner = match.group(1).split()
    out = subprocess.run([sys.executable, *inner[1:]], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert Path(out.stdout.strip()).is_file(), f"{' '.join(inner)} printed {out.stdout!r}, not a file"


@pytest.mark.parametrize("line", COMMANDS)
def test_readme_command(line):
    if line.startswith("export "):
        return _check_export(line)
    words = shlex.split(line)
    program = Path(words[0]).name
    if program == "make":
        _check_make(words)
    elif program == "mireg":
        _check_mireg(words)
    elif program == "instance_registration_node":
        _check_node(words)
    elif program == "ros2":
        _check_ros2(words)
    else:
        pytest.fail(f"the README shows `{line}`: teach test/test_docs.py how to check it")


def test_every_mireg_command_the_readme_names_runs_its_help():
    names = sorted({shlex.split(c)[1] for c in COMMANDS if Path(shlex.split(c)[0]).name == "mireg"})
    assert names
    mireg = Path(sys.executable).with_name("mireg")
    for argv in [["--help"], *([name, "--help"] for name in names)]:
        out = subprocess.run([str(mireg), *argv], cwd=ROOT, capture_output=True, text=True, timeout=300)
        assert out.returncode == 0 and "usage: mireg" in out.stdout, (argv, out.stderr)
