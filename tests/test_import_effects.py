"""What importing the package does: nothing to the environment, no process, no matplotlib
backend, and the commands start without torch. Each probe runs in a fresh interpreter.
"""

from __future__ import annotations

import pytest
from helpers import PIPELINE_MODULES as MODULES
from helpers import fresh_python

# Third-party libraries that change os.environ when imported (pinned versions, pyproject):
# they are imported before the snapshot, so that what remains is pipeline's own doing.
#   sklearn/__init__.py: os.environ.setdefault("KMP_DUPLICATE_LIB_OK", "True") and
#                        os.environ.setdefault("KMP_INIT_AT_FORK", "FALSE")
#   mlflow/__init__.py:  set_telemetry_client() sets _MLFLOW_TELEMETRY_SESSION_ID
#                        (mlflow/telemetry/client.py), unless telemetry is disabled
# torch, numpy, scipy, matplotlib, hydra, omegaconf, pandas, OpenEXR, PIL set nothing.
LIBRARY_ENV = {
    "sklearn": {"KMP_DUPLICATE_LIB_OK", "KMP_INIT_AT_FORK"},
    "mlflow": {"_MLFLOW_TELEMETRY_SESSION_ID"},
}

IMPORT_PROBE = r"""
import importlib, json, os, pkgutil, sys, traceback

LIBRARIES = __LIBRARIES__
SPAWNS = {"subprocess.Popen", "os.system", "os.fork", "os.forkpty", "os.posix_spawn",
          "os.spawn", "os.exec"}
phase = ["libraries"]
env_writes, spawns, watched = [], [], []


def origin():
    # Innermost frame outside this probe and the os/subprocess modules, and the innermost
    # frame in pipeline/ (what imported the library that did it, when one did).
    frames = [f for f in traceback.extract_stack()[:-2]
              if f.filename not in ("<string>", "<frozen os>")
              and not f.filename.endswith(("/os.py", "/subprocess.py"))]
    inner = frames[-1] if frames else None
    own = [f for f in frames if "/pipeline/" in f.filename]
    fmt = lambda f: f"{f.filename}:{f.lineno}" if f else None
    return fmt(inner), fmt(own[-1] if own else None)


def audit(event, args):
    if event in ("os.putenv", "os.unsetenv"):
        key = args[0].decode() if isinstance(args[0], bytes) else str(args[0])
        env_writes.append([phase[0], event, key, *origin()])
    elif event in SPAWNS:
        spawns.append([phase[0], event, repr(args)[:200], *origin()])


class Watch:
    # Records who imports matplotlib.pyplot; finds nothing itself.
    def find_spec(self, name, path=None, target=None):
        if name == "matplotlib.pyplot":
            watched.append([phase[0], name, *origin()])
        return None


sys.addaudithook(audit)
sys.meta_path.insert(0, Watch())

import matplotlib

def backend():
    rc = matplotlib.rcParams
    getter = getattr(rc, "_get_backend_or_none", None)  # never resolves the backend
    return getter() if getter else dict.__getitem__(rc, "backend")

uses = []
real_use = matplotlib.use
def use(*args, **kwargs):
    uses.append([phase[0], repr(args), *origin()])
    return real_use(*args, **kwargs)
matplotlib.use = use

env_start = dict(os.environ)
for name in LIBRARIES:
    importlib.import_module(name)
env_libraries = dict(os.environ)
backend_before = backend()
pyplot_before = "matplotlib.pyplot" in sys.modules

phase[0] = "pipeline"
import pipeline

def fail(name):
    raise ImportError(f"walk_packages could not import {name}")

walked = [m.name for m in pkgutil.walk_packages(pipeline.__path__, "pipeline.", onerror=fail)
          if m.name.rsplit(".", 1)[-1] != "__main__"]
for name in walked:
    importlib.import_module(name)
phase[0] = "done"

me = os.getpid()
children = []
for entry in os.listdir("/proc"):
    if entry.isdigit():
        try:
            stat = open(f"/proc/{entry}/stat").read()
        except OSError:
            continue
        if int(stat.rsplit(")", 1)[1].split()[1]) == me:
            children.append(stat[:100])

diff = lambda a, b: {k: [a.get(k), b.get(k)] for k in sorted(set(a) | set(b)) if a.get(k) != b.get(k)}
print(json.dumps({
    "walked": walked,
    "library_env": diff(env_start, env_libraries),
    "pipeline_env": diff(env_libraries, dict(os.environ)),
    "env_writes": env_writes,
    "spawns": spawns,
    "children": children,
    "backend": [backend_before, backend()],
    "pyplot": [pyplot_before, "matplotlib.pyplot" in sys.modules],
    "pyplot_importers": watched,
    "use_calls": uses,
}))
"""


@pytest.fixture(scope="module")
def import_probe() -> dict:
    """Every pipeline module imported, one after another, in a fresh interpreter."""
    code = IMPORT_PROBE.replace("__LIBRARIES__", repr(sorted(LIBRARY_ENV)))
    return fresh_python(code)


def test_every_module_is_imported_by_the_walk(import_probe):
    """The walk reaches every file under pipeline/ (a folder without ``__init__.py``
    would hide its modules from it, and from setuptools' package list)."""
    on_disk = {name for name in MODULES if name != "pipeline" and not name.endswith("__main__")}
    assert set(import_probe["walked"]) == on_disk


def test_importing_pipeline_leaves_the_environment_alone(import_probe):
    """os.environ is unchanged by importing every module, once the libraries that set
    variables themselves (:data:`LIBRARY_ENV`) are loaded; those set only what is listed."""
    for key in import_probe["library_env"]:
        assert any(key in keys for keys in LIBRARY_ENV.values()), (
            f"a library set {key}; add it to LIBRARY_ENV with where it is set",
            import_probe["env_writes"],
        )
    writes = [w for w in import_probe["env_writes"] if w[0] == "pipeline"]
    assert import_probe["pipeline_env"] == {}, writes
    # Set and restored again counts too: nothing writes the environment while importing.
    assert writes == [], "phase, event, key, where, pipeline frame"


def test_importing_pipeline_starts_no_process(import_probe):
    spawns = [s for s in import_probe["spawns"] if s[0] == "pipeline"]
    assert spawns == [], "phase, event, args, where, pipeline frame"
    assert import_probe["children"] == []


def test_importing_pipeline_leaves_matplotlib_alone(import_probe):
    """No module picks a backend or loads pyplot (which picks one) when imported: a
    figure is drawn with ``matplotlib.figure.Figure`` where it is made."""
    assert import_probe["use_calls"] == []
    assert import_probe["backend"][1] == import_probe["backend"][0]
    assert import_probe["pyplot"] == [False, False], import_probe["pyplot_importers"]


TORCH_PROBE = r"""
import importlib, json, sys, traceback

importers = []

class Watch:
    def find_spec(self, name, path=None, target=None):
        if name == "torch":
            importers.append([f"{f.filename}:{f.lineno}" for f in traceback.extract_stack()
                              if "/pipeline/" in f.filename])
        return None

sys.meta_path.insert(0, Watch())
loaded = {}
for name in __MODULES__:
    importlib.import_module(name)
    loaded[name] = "torch" in sys.modules
print(json.dumps({"loaded": loaded, "importers": importers}))
"""


def test_commands_start_without_torch():
    """``import pipeline``, the job (``python -m pipeline``: ``pipeline.__main__``,
    ``pipeline.app``) and ``python -m pipeline.tables`` do not load torch: a rerun whose
    stages are all cached starts in a second or two. (Each name is imported in turn, in
    one fresh interpreter; torch is imported inside the stages that compute.)"""
    names = ["pipeline", "pipeline.tables", "pipeline.app", "pipeline.__main__"]
    probe = fresh_python(TORCH_PROBE.replace("__MODULES__", repr(names)))
    assert probe["loaded"] == dict.fromkeys(names, False), probe["importers"]
