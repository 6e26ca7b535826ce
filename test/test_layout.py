"""The package's layout: no import circle among its modules, every folder a package that says
what it is. Static (the source is parsed, nothing imported), so a circle hidden in a function's
body counts as much as one at the top of a file."""
import ast
from pathlib import Path

PACKAGE_ROOT = Path(__file__).resolve().parents[1] / "multi_instance_reg"


def module_names(package_dir: Path) -> dict[str, tuple[Path, bool]]:
    """Dotted module name -> (file, is it a package's __init__)."""
    names = {}
    for path in sorted(package_dir.rglob("*.py")):
        parts = list(path.relative_to(package_dir.parent).with_suffix("").parts)
        is_package = parts[-1] == "__init__"
        names[".".join(parts[:-1] if is_package else parts)] = (path, is_package)
    return names


def import_graph(package_dir: Path) -> dict[str, set[str]]:
    """Each module of the package -> the package's modules it imports anywhere in its body
    (``from a.b import c`` imports the module a.b.c when there is one, else a.b)."""
    modules = module_names(package_dir)
    top = package_dir.name

    def known(name: str) -> str | None:
        while name and name not in modules:
            name = name.rpartition(".")[0]
        return name or None

    graph = {name: set() for name in modules}
    for name, (path, is_package) in modules.items():
        here = name if is_package else name.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    parts = here.split(".")
                    base = ".".join(parts[:len(parts) - node.level + 1] + ([node.module] if node.module else []))
                targets = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in modules else base
                           for alias in node.names]
            else:
                continue
            for target in targets:
                if target == top or target.startswith(top + "."):
                    found = known(target)
                    if found and found != name:
                        graph[name].add(found)
    return graph


def find_circle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import circle (its modules, the first repeated at the end), or None."""
    state = {}          # absent: not seen; 1: on the current path; 2: done, no circle through it
    path = []

    def visit(node):
        state[node] = 1
        path.append(node)
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                return path[path.index(nxt):] + [nxt]
            if nxt not in state:
                circle = visit(nxt)
                if circle:
                    return circle
        path.pop()
        state[node] = 2
        return None

    for start in sorted(graph):
        if start not in state:
            circle = visit(start)
            if circle:
                return circle
    return None


def test_no_module_of_the_package_imports_itself_in_a_circle():
    graph = import_graph(PACKAGE_ROOT)
    assert len(graph) > 50 and graph["multi_instance_reg.rgbd.pipeline"], "the import graph came out empty"
    circle = find_circle(graph)
    assert circle is None, "import circle: " + " -> ".join(circle)


def test_a_circle_is_found_also_when_one_side_imports_inside_a_function(tmp_path):
    package = tmp_path / "pkg"
    (package / "sub").mkdir(parents=True)
    (package / "__init__.py").write_text("")
    (package / "sub" / "__init__.py").write_text("")
    (package / "sub" / "a.py").write_text("from ..b import helper\n")
    (package / "b.py").write_text("def helper():\n    from .sub import a\n    return a\n")
    (package / "c.py").write_text("import pkg.b\nfrom pkg.sub.a import x\n")
    graph = import_graph(package)
    assert graph == {"pkg": set(), "pkg.sub": set(), "pkg.sub.a": {"pkg.b"}, "pkg.b": {"pkg.sub.a"},
                     "pkg.c": {"pkg.b", "pkg.sub.a"}}
    assert find_circle(graph) == ["pkg.b", "pkg.sub.a", "pkg.b"]
    (package / "b.py").write_text("def helper():\n    return 1\n")
    assert find_circle(import_graph(package)) is None


def test_every_folder_is_a_package_that_says_what_it_holds():
    # A folder without __init__.py is left out of the wheel and the colcon install
    # (find_packages); its docstring is where a reader learns what the folder is for.
    for folder in sorted({p.parent for p in PACKAGE_ROOT.rglob("*.py")}):
        init = folder / "__init__.py"
        assert init.exists(), f"{folder.relative_to(PACKAGE_ROOT.parent)} has no __init__.py"
        assert ast.get_docstring(ast.parse(init.read_text())), f"{init.relative_to(PACKAGE_ROOT.parent)} has no docstring"
