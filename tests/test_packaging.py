"""Packaging: one `vqtouch` namespace in site-packages, importable from outside the checkout."""

import ast
import os
import re
import shutil
import subprocess
import sys
import venv
from pathlib import Path


REPO = Path(__file__).resolve().parents[1]
PACKAGE_FOLDERS = ("core", "plugins", "conditioners", "sensors")


def test_code_imports_only_through_the_vqtouch_namespace(package_sources):
    bad = []
    for path in package_sources:
        for node in ast.walk(ast.parse(path.read_text())):
            names = []
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            bad += [f"{path.relative_to(REPO)}: {name}" for name in names if name.split(".")[0] in PACKAGE_FOLDERS]
    assert not bad, bad


#: The core files that may name a plugin module, as data only: the shims of what left the core.
SHIM_TABLES = ("deprecations.py", "__init__.py")


def test_core_never_imports_plugins():
    for path in (REPO / "core").rglob("*.py"):
        text = path.read_text()
        for other in ("vqtouch.plugins", "vqtouch.conditioners", "vqtouch.sensors"):
            if path.name in SHIM_TABLES:
                statement = re.search(rf"^\s*(from|import) {re.escape(other)}", text, re.M)
                assert statement is None, f"{path} imports {other}: core must not depend on plugins"
            else:
                assert other not in text, f"{path} mentions {other}: core must not depend on plugins"


def test_every_package_folder_has_an_init():
    for folder in PACKAGE_FOLDERS:
        for directory in [REPO / folder, *[p for p in (REPO / folder).rglob("*") if p.is_dir()]]:
            if directory.name != "__pycache__" and any(directory.glob("*.py")):
                assert (directory / "__init__.py").is_file(), f"{directory} is not a package (it would be left out)"


def test_wheel_installs_one_namespace_and_imports_outside_checkout(tmp_path):
    # Built from a copy without the checkout's build leftovers: an egg-info left by an earlier build lists
    # files (SOURCES.txt) that a clean checkout's wheel would not get, and hid the missing weights.
    source = tmp_path / "source"
    leftovers = ("build", "dist", "*.egg-info", ".venv", ".git", "runs", "__pycache__", ".pytest_cache")
    shutil.copytree(REPO, source, ignore=shutil.ignore_patterns(*leftovers))
    dist = tmp_path / "dist"
    build = subprocess.run(
        [sys.executable, "-m", "build", "--wheel", "--no-isolation", "--outdir", str(dist), str(source)],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=600,
    )
    assert build.returncode == 0, build.stderr[-2000:]
    wheel = next(dist.glob("vqtouch-*.whl"))

    env_dir = tmp_path / "venv"
    venv.EnvBuilder(with_pip=False).create(env_dir)
    python = env_dir / "bin" / "python"
    site = Path(
        subprocess.check_output(
            [str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"], text=True
        ).strip()
    )
    install = subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "install",
            "--quiet",
            "--no-deps",
            "--no-index",
            "--target",
            str(site),
            str(wheel),
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert install.returncode == 0, install.stderr[-2000:]

    top_level = sorted(
        p.name for p in site.iterdir() if not p.name.endswith((".dist-info", ".pth")) and p.name != "__pycache__"
    )
    assert top_level == ["bin", "vqtouch"] or top_level == ["vqtouch"], top_level
    installed = {p.relative_to(site / "vqtouch").parts[0] for p in (site / "vqtouch").rglob("*.py")}
    assert installed == set(PACKAGE_FOLDERS)
    assert (site / "vqtouch" / "sensors" / "__init__.py").is_file()

    # Dependencies (torch, pydantic, ...) come from the test environment, appended after the fresh site.
    deps = [p for p in sys.path if p.endswith("site-packages")]
    (site / "zz_deps.pth").write_text("\n".join(deps) + "\n")
    code = (
        "import vqtouch.core, sys; from vqtouch.core import load_plugins; host = load_plugins(autoload=False); "
        "print(vqtouch.core.__file__); print(sorted(host.registry('conditioner').names()));"
        "import importlib.util as u; print(u.find_spec('core'), u.find_spec('plugins'))"
    )
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in {"PYTHONPATH"}}
    result = subprocess.run(
        [str(python), "-c", code], capture_output=True, text=True, cwd=outside, env=env, timeout=300
    )
    assert result.returncode == 0, result.stderr[-2000:]
    lines = result.stdout.strip().splitlines()
    assert lines[0].startswith(str(site)), lines
    conditioners = [
        "clip",
        "label",
        "sensor",
        "tactile",
        "tactile_codes",
        "text",
        "text_scratch",
        "visual",
        "visual_cnn",
    ]
    assert lines[1] == str(conditioners)
    assert lines[2] == "None None"

    # The bundled checkpoints ship in the wheel (a non-editable install once had none), byte for
    # byte, and open from the installed package outside the checkout.
    shipped = REPO / "plugins" / "pretrained" / "weights"
    expected = sorted(path.relative_to(shipped) for path in shipped.rglob("*.safetensors"))
    installed_weights = site / "vqtouch" / "plugins" / "pretrained" / "weights"
    assert (
        expected
        and sorted(path.relative_to(installed_weights) for path in installed_weights.rglob("*.safetensors")) == expected
    )
    assert all((installed_weights / name).read_bytes() == (shipped / name).read_bytes() for name in expected)
    recipes = sorted(path.name for path in (REPO / "plugins" / "pretrained" / "recipes").glob("*.toml"))
    installed_recipes = site / "vqtouch" / "plugins" / "pretrained" / "recipes"
    assert recipes and sorted(path.name for path in installed_recipes.glob("*.toml")) == recipes
    bundle_code = (
        "from vqtouch.core import load_plugins; from vqtouch.core.checkpoint import open_pretrained; "
        "host = load_plugins(autoload=False); bundle = open_pretrained('pretrained:tour', host); "
        "print(bundle.folder); print(len(bundle.conditioners), bundle.generator is not None)"
    )
    opened = subprocess.run(
        [str(python), "-c", bundle_code], capture_output=True, text=True, cwd=outside, env=env, timeout=300
    )
    assert opened.returncode == 0, opened.stderr[-2000:]
    folder, counts = opened.stdout.strip().splitlines()[-2:]
    assert folder.startswith(str(site)) and counts == "4 True", opened.stdout


# -- dependencies: lower bounds in the library, the verified pair in constraints.txt ---------------


def _project():
    import tomllib

    return tomllib.loads((REPO / "pyproject.toml").read_text())["project"]


def _requirements(lines):
    from packaging.requirements import Requirement

    return [Requirement(line) for line in lines]


def test_library_dependencies_have_lower_bounds_not_exact_pins():
    project = _project()
    everything = [*project["dependencies"], *(r for extra in project["optional-dependencies"].values() for r in extra)]
    pinned = [str(r) for r in _requirements(everything) if any(s.operator in ("==", "===") for s in r.specifier)]
    assert not pinned, f"exact pins belong in constraints.txt, not in the library's dependencies: {pinned}"
    torch = next(r for r in _requirements(project["dependencies"]) if r.name == "torch")
    assert any(s.operator == ">=" for s in torch.specifier), torch


def test_constraints_pin_exactly_the_verified_torch_pair_and_tacto():
    lines = [line.split("#")[0].strip() for line in (REPO / "constraints.txt").read_text().splitlines()]
    pins = {r.name: str(r.specifier) for r in _requirements(line for line in lines if line)}
    # tacto: the release whose config_digit.yml the digit family reads (tests/test_digit_design.py);
    # torchmetrics and torch-fidelity: the metric implementations the tests' closed forms were checked on.
    assert pins == {
        "torch": "==2.15.0",
        "torchvision": "==0.29.2",
        "tacto": "==0.0.3",
        "torchmetrics": "==1.9.0",
        "torch-fidelity": "==0.4.0",
    }
    # The pinned versions satisfy the library's own bounds (else pip could not resolve with the file).
    project = _project()
    bounds = _requirements(
        [
            *project["dependencies"],
            *project["optional-dependencies"]["clip"],
            *project["optional-dependencies"]["metrics"],
        ]
    )
    for requirement in bounds:
        if requirement.name in pins:
            assert requirement.specifier.contains(pins[requirement.name].removeprefix("==")), requirement


def test_open_clip_is_only_in_the_clip_extra_and_imported_only_lazily(package_sources):
    project = _project()
    owners = [
        group
        for group, lines in [("dependencies", project["dependencies"]), *project["optional-dependencies"].items()]
        if any(r.name == "open_clip_torch" for r in _requirements(lines))
    ]
    assert owners == ["clip"]
    # Only the one open_clip module imports open_clip, and only inside a function (importing vqtouch never
    # needs it): the clip and text conditioners and the clip_score metric all go through it.
    importers = []
    for path in package_sources:
        tree = ast.parse(path.read_text())
        in_functions = {
            id(inner)
            for node in ast.walk(tree)
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))
            for inner in ast.walk(node)
        }
        for node in ast.walk(tree):
            names = (
                [alias.name for alias in node.names]
                if isinstance(node, ast.Import)
                else [node.module or ""]
                if isinstance(node, ast.ImportFrom)
                else []
            )
            if any(name.split(".")[0] == "open_clip" for name in names):
                importers.append((path.relative_to(REPO).as_posix(), id(node) not in in_functions))
    assert importers and {path for path, _ in importers} == {"plugins/evaluation/open_clip_towers.py"}, importers
    assert not any(at_module_level for _, at_module_level in importers), importers


def test_makefile_installs_with_the_constraints_and_the_clip_and_metrics_extras():
    makefile = (REPO / "Makefile").read_text()
    installs = [line for line in makefile.splitlines() if "pip install" in line and " -e " in line]
    assert len(installs) == 1, installs
    assert "-c constraints.txt" in installs[0] and "'.[test,clip,metrics]'" in installs[0], installs[0]
    stamp_rule = next(line for line in makefile.splitlines() if line.startswith("$(STAMP):"))
    assert "constraints.txt" in stamp_rule, "editing constraints.txt must trigger a reinstall"
    # tacto only for its DIGIT design file: its own dependencies (pyrender, OpenGL) must not be installed.
    tacto = [line for line in makefile.splitlines() if "pip install" in line and line.rstrip().endswith(" tacto")]
    assert len(tacto) == 1 and "--no-deps" in tacto[0] and "-c constraints.txt" in tacto[0], tacto
