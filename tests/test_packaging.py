"""What a new user installs and reads: pictures, links, license, typing marker, registry."""

import re
import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import pytest

import constrained_particles
import envs

ROOT = Path(__file__).resolve().parents[1]


def tracked_files() -> set[str]:
    """Paths git tracks in this checkout (the files a fresh clone has)."""
    out = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True)
    if out.returncode != 0:
        pytest.fail(f"git ls-files failed (the packaging tests need a git checkout): {out.stderr}")
    return set(out.stdout.splitlines())


def local_links(markdown: str, images: bool) -> list[str]:
    """Relative link targets in ``markdown``: images ``![..](x)`` or other links ``[..](x)``."""
    pattern = r"!\[[^\]]*\]\(([^)\s]+)\)" if images else r"(?<!!)\[[^\]]*\]\(([^)\s]+)\)"
    return [t.split("#")[0] for t in re.findall(pattern, markdown)
            if not re.match(r"[a-z]+://|#|mailto:", t)]


def test_every_readme_image_is_a_tracked_file():
    readme = (ROOT / "README.md").read_text()
    images = local_links(readme, images=True)
    assert len(images) >= 4
    missing = sorted(set(images) - tracked_files())
    assert not missing, f"README shows images git does not track: {missing}"


def test_every_readme_link_stays_inside_the_repository():
    readme = (ROOT / "README.md").read_text()
    links = local_links(readme, images=False)
    assert "docs/physics.md" in links
    missing = sorted(set(links) - tracked_files())
    assert not missing, f"README links to files git does not track: {missing}"
    assert "shared/" not in readme and "DESIGN.md" not in readme


def test_license_changelog_and_typing_markers_are_tracked():
    files = tracked_files()
    assert {"LICENSE", "CHANGELOG.md", "docs/physics.md", "constrained_particles/py.typed",
            "envs/py.typed", "verification/py.typed"} <= files
    assert (ROOT / "LICENSE").read_text().startswith("MIT License")
    assert constrained_particles.__version__ in (ROOT / "CHANGELOG.md").read_text()


def test_pyproject_metadata():
    text = (ROOT / "pyproject.toml").read_text()
    assert re.search(r'^license = "MIT"$', text, re.M)  # the SPDX form, not a table
    version = re.search(r'^version = "([^"]+)"$', text, re.M).group(1)
    assert version == constrained_particles.__version__
    include = re.search(r"^include = \[(.*)\]$", text, re.M).group(1)
    assert "benchmarks" not in include and "tests" not in include
    deps = text[text.index("dependencies = ["):text.index("]", text.index("dependencies = ["))]
    assert re.search(r'"numba>=0\.59,<0\.\d+"', deps)  # (bounded: its internals are used)


def test_wheel_packages_are_the_four_top_level_ones():
    """setuptools' package discovery with the project's include patterns: the three library
    packages and the command line above them, whose console script is cparticles.cli:main."""
    from setuptools import find_packages

    text = (ROOT / "pyproject.toml").read_text()
    include = re.findall(r'"([^"]+)"', re.search(r"^include = \[(.*)\]$", text, re.M).group(1))
    top = {p.split(".")[0] for p in find_packages(str(ROOT), include=include)}
    assert top == {"constrained_particles", "envs", "verification", "cparticles"}
    assert (ROOT / "cparticles" / "bench.py").is_file()  # a module of a shipped package
    assert re.search(r'^cparticles = "cparticles\.cli:main"$', text, re.M)


def test_python_m_cparticles_is_the_console_script():
    import sys

    out = subprocess.run([sys.executable, "-m", "cparticles", "--version"], cwd=ROOT,
                         capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == f"cparticles {constrained_particles.__version__}"


def test_pprint_registry_lists_the_envs_together():
    listing = gym.pprint_registry(disable_print=True)
    blocks = listing.split("=====")
    together = [b for b in blocks if all(i in b for i in envs.ENV_IDS)]
    assert len(together) == 1
    assert "===== cparticles =====" in listing
    for env_id in envs.ENV_IDS:
        assert gym.spec(env_id).id == env_id  # ids unchanged, no namespace


def test_readme_is_a_short_product_page():
    readme = (ROOT / "README.md").read_text()
    lines = readme.splitlines()
    assert len(lines) <= 300, f"README.md has {len(lines)} lines; at most 300"
    assert not re.search(r"\bissues?\s+#?\d+", readme, re.I), "README mentions an issue number"
    assert "used to" not in readme.lower()
    # the two commands, the second verbatim as CI runs it
    assert "git clone " in readme and "cd constrained-particles" in readme
    assert 'python -m pip install -e ".[test]" && python -m pytest' in readme
    for command in ("run", "demo", "view", "verify", "bench", "train", "evaluate"):
        assert f"| `cparticles {command}" in readme, f"command table lacks {command}"
    for env_id in envs.ENV_IDS:
        assert f"| `{env_id}` |" in readme, f"task table lacks {env_id}"


def test_docs_index_links_every_docs_page():
    docs = ROOT / "docs"
    index = (docs / "README.md").read_text()
    linked = {target for target in local_links(index, images=False)}
    pages = {p.name for p in docs.glob("*.md") if p.name != "README.md"}
    assert pages, "no pages under docs/"
    assert not pages - linked, f"docs/README.md does not link {sorted(pages - linked)}"
    assert "docs/README.md" in local_links((ROOT / "README.md").read_text(), images=False)


def test_docs_links_and_images_are_tracked_files():
    tracked = tracked_files()
    for page in sorted((ROOT / "docs").rglob("*.md")):
        text = page.read_text()
        for target in local_links(text, images=False) + local_links(text, images=True):
            path = (page.parent / target).resolve().relative_to(ROOT).as_posix()
            assert path in tracked, f"{page.relative_to(ROOT)} links to untracked {target}"


# ------------------------------------------------------------------ the Numba cache location
# Each case runs in a fresh interpreter: constrained_particles.jit decides its directory once
# per process, from the environment at that time.

JITTED = '''
from constrained_particles.jit import njit

@njit
def twice(x):
    return 2.0 * x
'''

PROBE = '''
import sys
from constrained_particles import jit
import jitted
value = jitted.twice(1.5)
print(jit.cache_dir())
print(jitted.twice.stats.cache_path)
stats = jitted.twice.stats
print(value, sum(stats.cache_misses.values()), sum(stats.cache_hits.values()))
'''


def probe(tmp_path: Path, stderr: int | None = None,
          **environ: str | None) -> subprocess.CompletedProcess:
    """Compile ``jitted.twice`` (a module in ``tmp_path/src``) in a fresh interpreter with
    ``environ`` applied to the current environment (None removes a variable); its stderr is
    captured, or goes to the file descriptor ``stderr``."""
    import os
    import sys

    src = tmp_path / "src"
    src.mkdir(exist_ok=True)
    (src / "jitted.py").write_text(JITTED)
    env = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CACHE_DIR", "XDG_CACHE_HOME")}
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), str(src)])
    for key, value in environ.items():
        if value is None:
            env.pop(key, None)
        else:
            env[key] = value
    return subprocess.run([sys.executable, "-c", PROBE], env=env, cwd=tmp_path,
                          stdout=subprocess.PIPE,
                          stderr=subprocess.PIPE if stderr is None else stderr, text=True,
                          timeout=300)


def cached_files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.rglob("*") if p.suffix in (".nbi", ".nbc"))


def test_numba_cache_honours_numba_cache_dir(tmp_path):
    out = probe(tmp_path, NUMBA_CACHE_DIR=str(tmp_path / "numba"), XDG_CACHE_HOME=None)
    assert out.returncode == 0, out.stderr
    root, path, counts = out.stdout.splitlines()
    assert root == str(tmp_path / "numba")
    assert Path(path).parent == tmp_path / "numba"
    assert counts == "3.0 1 0"  # compiled once, nothing loaded
    files = cached_files(tmp_path / "numba")  # an index and the machine code
    assert [p.suffix for p in files] == [".nbc", ".nbi"]
    assert all(p.name.startswith("jitted.twice-") for p in files)
    assert cached_files(tmp_path / "src") == []  # nothing next to the source
    again = probe(tmp_path, NUMBA_CACHE_DIR=str(tmp_path / "numba"), XDG_CACHE_HOME=None)
    assert again.stdout.splitlines()[2] == "3.0 0 1"  # the second process loads it


def test_numba_cache_defaults_to_the_user_cache_directory(tmp_path):
    import numba

    tag = f"numba-{numba.__version__}-{sys.implementation.cache_tag}"
    out = probe(tmp_path, XDG_CACHE_HOME=str(tmp_path / "xdg"))
    assert out.returncode == 0, out.stderr
    assert out.stdout.splitlines()[0] == str(tmp_path / "xdg" / "constrained-particles" / tag)
    assert len(cached_files(tmp_path / "xdg")) == 2
    # no XDG_CACHE_HOME (or a relative one, which the XDG spec says to ignore): ~/.cache
    for xdg in (None, "relative/path"):
        out = probe(tmp_path, XDG_CACHE_HOME=xdg, HOME=str(tmp_path / "home"))
        assert out.returncode == 0, out.stderr
        expected = tmp_path / "home" / ".cache" / "constrained-particles" / tag
        assert out.stdout.splitlines()[0] == str(expected)
    assert not (tmp_path / "relative").exists()
    assert cached_files(tmp_path / "src") == [] and out.stderr == ""  # (loaded: not a word)


def test_a_cached_kernel_compiles_again_when_a_module_beside_it_changes(tmp_path):
    """A kernel's machine code can hold functions of other modules compiled in (the fused step
    calls the elements of kernels.py and fused_accel.py): after an edit to a module in its
    folder, the old machine code is not loaded."""
    folder = {"NUMBA_CACHE_DIR": str(tmp_path / "numba"), "XDG_CACHE_HOME": None}
    counts = [probe(tmp_path, **folder).stdout.splitlines()[2] for _ in range(2)]
    assert counts == ["3.0 1 0", "3.0 0 1"]  # compiled, then loaded
    (tmp_path / "src" / "helper.py").write_text("SCALE = 2.0\n")
    counts = [probe(tmp_path, **folder).stdout.splitlines()[2] for _ in range(2)]
    assert counts == ["3.0 1 0", "3.0 0 1"]  # compiled again, then loaded


def test_source_stamp_covers_the_folder_and_the_package(tmp_path):
    from constrained_particles import jit

    (tmp_path / "a.py").write_text("x = 1\n")
    (tmp_path / "b.py").write_text("y = 1\n")
    before = jit.source_stamp(str(tmp_path / "a.py"))
    assert before == jit.source_stamp(str(tmp_path / "b.py"))  # one stamp for the folder
    assert before[1] == jit.source_stamp(jit.__file__)[1]  # and the package's modules
    (tmp_path / "b.py").write_text("y = 2\n")
    jit._folder_digest.cache_clear()  # (read once per process)
    after = jit.source_stamp(str(tmp_path / "a.py"))
    assert after[0] != before[0] and after[1] == before[1]


@pytest.mark.parametrize("variable", ["NUMBA_CACHE_DIR", "XDG_CACHE_HOME"])
def test_unusable_cache_directory_compiles_in_memory_with_one_line(tmp_path, variable):
    blocker = tmp_path / "a-file"
    blocker.write_text("")  # a folder cannot be made below a file, not even by root
    out = probe(tmp_path, **{variable: str(blocker / "cache")})
    assert out.returncode == 0, out.stderr
    root, path, counts = out.stdout.splitlines()
    assert root == path == "None" and counts == "3.0 1 0"  # no cache: compiled in memory
    lines = out.stderr.splitlines()
    assert len(lines) == 1, out.stderr
    assert lines[0].startswith("constrained-particles: cache directory") and "memory" in lines[0]
    assert str(blocker) in lines[0]
    assert cached_files(tmp_path) == []


def on_a_terminal(tmp_path: Path, **environ: str | None) -> str:
    """What :func:`probe` writes to stderr when stderr is a terminal (a pseudo-terminal)."""
    import os
    import pty

    main, child = pty.openpty()
    try:
        out = probe(tmp_path, stderr=child, **environ)
        os.close(child)
        child = -1
        assert out.returncode == 0
        text = b""
        while True:
            try:
                chunk = os.read(main, 4096)
            except OSError:  # Linux: EIO once the child side is closed and drained
                break
            if not chunk:
                break
            text += chunk
    finally:
        os.close(main)
        if child >= 0:
            os.close(child)
    return text.decode()


def compile_notice_only(stderr: str) -> bool:
    """True if ``stderr`` holds nothing but the first compile's one-line notice."""
    lines = stderr.splitlines()
    return len(lines) == 1 and lines[0].startswith("constrained-particles: compiling kernels")


def test_a_first_compile_says_so_once_on_a_terminal_or_not(tmp_path):
    cache = str(tmp_path / "numba")
    said = on_a_terminal(tmp_path, NUMBA_CACHE_DIR=cache)  # an empty cache: it compiles
    assert said.count("compiling kernels") == 1, said
    assert said.strip().startswith("constrained-particles: compiling kernels") and cache in said
    assert on_a_terminal(tmp_path, NUMBA_CACHE_DIR=cache) == ""  # loaded from the cache
    piped = probe(tmp_path, NUMBA_CACHE_DIR=str(tmp_path / "other"))  # compiles, into a pipe
    assert piped.returncode == 0 and piped.stdout.splitlines()[2] == "3.0 1 0"
    assert compile_notice_only(piped.stderr), piped.stderr  # (a notebook, a CI log)
    again = probe(tmp_path, NUMBA_CACHE_DIR=str(tmp_path / "other"))  # loaded: nothing said
    assert again.stdout.splitlines()[2] == "3.0 0 1" and again.stderr == ""


def test_njit_refuses_a_cache_option():
    from constrained_particles import jit

    with pytest.raises(ValueError, match="options"):
        jit.njit(cache=True)


def test_every_compiled_function_uses_the_jit_module():
    """No numba.njit / numba.jit call outside constrained_particles/jit.py in the shipped
    packages: each would cache into the installed package, or not at all."""
    offenders = []
    for package in ("constrained_particles", "envs", "verification"):
        for path in sorted((ROOT / package).rglob("*.py")):
            if path == ROOT / "constrained_particles" / "jit.py":
                continue
            text = path.read_text()
            for pattern in (r"cache\s*=\s*True", r"\bnumba\.n?jit\b",
                            r"from numba import.*\bn?jit\b"):
                offenders += [f"{path.relative_to(ROOT)}: {m.group(0)}"
                              for m in re.finditer(pattern, text)]
    assert offenders == []
    kernels = (ROOT / "constrained_particles" / "kernels.py").read_text()
    assert "from .jit import njit" in kernels


def damage(folder: Path, how: str) -> list[Path]:
    """Damage every cache file below ``folder`` as a full disk, a killed process or a copied
    home directory leaves them; returns the files damaged."""
    import random

    files = cached_files(folder)
    rng = random.Random(0)
    for path in files:
        data = path.read_bytes()
        if how == "truncated":
            path.write_bytes(data[: len(data) // 2])
        elif how == "random bytes":
            path.write_bytes(bytes(rng.randrange(256) for _ in data))
        elif how == "empty":
            path.write_bytes(b"")
        elif how == "data files only" and path.suffix == ".nbi":
            path.unlink()
        elif how == "another pickle protocol" and path.suffix == ".nbc":
            path.write_bytes(b"\x80\x09" + data[2:])  # as from a Python yet to come
    return files


@pytest.mark.parametrize("how", ["truncated", "random bytes", "empty", "data files only",
                                 "another pickle protocol"])
def test_a_damaged_cache_entry_is_set_aside_and_compiled_again(tmp_path, how):
    folder = {"NUMBA_CACHE_DIR": str(tmp_path / "numba"), "XDG_CACHE_HOME": None}
    assert probe(tmp_path, **folder).stdout.splitlines()[2] == "3.0 1 0"  # compiled, cached
    assert len(damage(tmp_path / "numba", how)) == 2
    out = probe(tmp_path, **folder)  # the first run after the damage succeeds
    assert out.returncode == 0, out.stderr
    assert out.stdout.splitlines()[2] == "3.0 1 0"  # compiled again
    lines = out.stderr.splitlines()
    assert len(lines) == 1, out.stderr  # one line: what was found, and where
    assert lines[0].startswith("constrained-particles: a compiled kernel in the cache could "
                               "not be loaded") and str(tmp_path / "numba") in lines[0]
    aside = sorted(p.name for p in (tmp_path / "numba").rglob("*.unreadable"))
    assert aside and all(name.startswith("jitted.twice-") for name in aside)
    again = probe(tmp_path, **folder)  # healed: loaded, nothing said
    assert again.stdout.splitlines()[2] == "3.0 0 1" and again.stderr == ""


def test_two_processes_filling_one_empty_cache_at_once(tmp_path):
    import os

    env = {k: v for k, v in os.environ.items() if k != "XDG_CACHE_HOME"}
    env["NUMBA_CACHE_DIR"] = str(tmp_path / "numba")
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), str(tmp_path / "src")])
    (tmp_path / "src").mkdir()
    (tmp_path / "src" / "jitted.py").write_text(JITTED)
    runs = [subprocess.Popen([sys.executable, "-c", PROBE], env=env, cwd=tmp_path,
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
            for _ in range(3)]
    outs = [run.communicate(timeout=300) for run in runs]
    assert [run.returncode for run in runs] == [0, 0, 0], outs
    assert all((err == "" or compile_notice_only(err)) and out.splitlines()[2].startswith("3.0 ")
               for out, err in outs)
    after = subprocess.run([sys.executable, "-c", PROBE], env=env, cwd=tmp_path,
                           capture_output=True, text=True, timeout=300)
    assert after.stdout.splitlines()[2] == "3.0 0 1" and after.stderr == ""  # loads the cache
    assert list((tmp_path / "numba").rglob("*.unreadable")) == []


FULL_DISK = '''
import errno
from numba.core import caching

def full(self, *args, **kwargs):
    raise OSError(errno.ENOSPC, "No space left on device")

caching.IndexDataCacheFile._save_index = full
caching.IndexDataCacheFile._save_data = full
import jitted
print(jitted.twice(1.5), jitted.twice(2.0))
'''


def test_a_cache_on_a_full_disk_keeps_the_kernels_in_memory_with_one_line_more(tmp_path):
    import os

    probe(tmp_path, NUMBA_CACHE_DIR=str(tmp_path / "other"))  # (writes src/jitted.py)
    env = {k: v for k, v in os.environ.items() if k != "XDG_CACHE_HOME"}
    env["NUMBA_CACHE_DIR"] = str(tmp_path / "numba")
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), str(tmp_path / "src")])
    out = subprocess.run([sys.executable, "-c", FULL_DISK], env=env, cwd=tmp_path,
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0 and out.stdout.split() == ["3.0", "4.0"], out.stderr
    lines = out.stderr.splitlines()  # the first compile's notice, then what went wrong
    assert compile_notice_only(lines[0]) and len(lines) == 2, out.stderr
    assert "could not be written to the cache" in lines[1], out.stderr
    assert "No space left on device" in lines[1]


def test_ci_tests_the_oldest_numba_and_numpy_pyproject_allows():
    """The lower bounds of numba and numpy in pyproject.toml are the versions .ci/oldest.txt
    pins for the oldest Pythons (CI runs the suite on them), and numba has an upper bound
    (its internals: constrained_particles.jit.NUMBA_INTERNALS)."""
    text = (ROOT / "pyproject.toml").read_text()
    numba = re.search(r'"numba>=([\d.]+),<([\d.]+)"', text)
    numpy = re.search(r'"numpy>=([\d.]+)', text)
    assert numba and numpy, "numba must be bounded on both sides"
    pins = {}
    for line in (ROOT / ".ci" / "oldest.txt").read_text().splitlines():
        if line and not line.startswith("#"):
            py, *reqs = line.split()
            pins[py] = dict(r.split("==") for r in reqs)
    assert pins["3.10"]["numba"].startswith(numba.group(1))
    assert pins["3.10"]["numpy"].startswith(numpy.group(1))
    def version(text: str) -> tuple[int, ...]:
        return tuple(int(part) for part in text.split("."))

    assert all(version(p["numba"]) < version(numba.group(2)) for p in pins.values())
    assert f"{sys.version_info[0]}.{sys.version_info[1]}" in pins  # (this Python has a line)
    assert ".ci/oldest.txt" in (ROOT / ".ci" / "run").read_text()
