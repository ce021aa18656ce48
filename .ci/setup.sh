#!/usr/bin/env bash
# Fresh-machine set-up for frepvdb (Debian bookworm, run as root or with sudo).
# Idempotent: each step checks before it acts, so a second run takes seconds.
set -euo pipefail
cd "$(dirname "$0")/.."

SYS_PY=/usr/bin/python3
if [ ! -x "$SYS_PY" ]; then
  echo "setup: $SYS_PY not found; frepvdb needs the system Python that python3-openvdb is built for." >&2
  exit 1
fi

need_apt=()
"$SYS_PY" -c "import pyopenvdb" 2>/dev/null || "$SYS_PY" -c "import openvdb" 2>/dev/null || need_apt+=(python3-openvdb)
"$SYS_PY" -c "import ensurepip, venv" 2>/dev/null || need_apt+=(python3-venv)
# GNU OpenMP: Numba's threading layer of choice (pipeline/__init__.py; TBB's slows down with use)
libs=$(/sbin/ldconfig -p 2>/dev/null || ldconfig -p 2>/dev/null || true)
[[ "$libs" == *"libgomp.so.1 "* ]] || need_apt+=(libgomp1)
# the compiled leaf builder (setup.py, pipeline/io/leafbuild.cpp) links the system's OpenVDB and
# boost.python, the ones python3-openvdb uses: their headers and a C++ compiler
# (wanted, not needed: without apt-get the install goes on and copyFromArray writes the grids)
want_apt=()
[ -f /usr/include/openvdb/openvdb.h ] || want_apt+=(libopenvdb-dev)
[ -f /usr/include/boost/python.hpp ] || want_apt+=(libboost-python-dev)
command -v g++ >/dev/null 2>&1 || want_apt+=(g++)
if [ ${#want_apt[@]} -gt 0 ] && command -v apt-get >/dev/null 2>&1; then
  need_apt+=("${want_apt[@]}")
fi
if [ ${#need_apt[@]} -gt 0 ]; then
  if ! command -v apt-get >/dev/null 2>&1; then
    cat >&2 <<MSG
setup: OpenVDB's Python module is not importable and apt-get is not available.
  On Debian/Ubuntu:  apt-get install python3-openvdb python3-venv
  Elsewhere:         conda install -c conda-forge openvdb   (the module is named 'openvdb' there)
  then create .venv from that Python with --system-site-packages and run: pip install -e '.[dev]'
  with NumPy on the major version that OpenVDB's module was built against (e.g. 'numpy==1.*')
MSG
    exit 1
  fi
  SUDO=""; [ "$(id -u)" = 0 ] || SUDO="sudo"
  echo "setup: apt-get install ${need_apt[*]}"
  $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y "${need_apt[@]}" >/dev/null 2>&1 || {
    $SUDO apt-get update >/dev/null
    $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y "${need_apt[@]}"
  }
fi

# The system's OpenVDB module is built against the system's NumPy; the venv sees the system's
# packages, so pip must keep NumPy on that major version (an extension built against NumPy 1.x
# runs on any later 1.x, not on 2.x).
SYS_NUMPY=$("$SYS_PY" -c "import numpy; print(numpy.__version__)" 2>/dev/null) || {
  echo "setup: $SYS_PY cannot import numpy; install python3-numpy (OpenVDB's Python module needs it)" >&2
  exit 1
}
SYS_NUMPY_MAJOR=${SYS_NUMPY%%.*}
NUMPY_PIN="numpy==${SYS_NUMPY_MAJOR}.*"

if [ ! -x .venv/bin/python ]; then
  echo "setup: creating .venv from $SYS_PY --system-site-packages"
  "$SYS_PY" -m venv --system-site-packages .venv
fi

stamp=.venv/.frepvdb-installed
built=(pipeline/io/_leafbuild*.so)
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ] || [ setup.py -nt "$stamp" ] \
   || [ pipeline/io/leafbuild.cpp -nt "$stamp" ] \
   || { [ ! -e "${built[0]}" ] && [ -f /usr/include/openvdb/openvdb.h ]; }; then
  echo "setup: pip install -e .[dev] ($NUMPY_PIN, the major version of the system's NumPy $SYS_NUMPY)"
  .venv/bin/python -m pip install --quiet --upgrade pip
  .venv/bin/python -m pip install --quiet -e '.[dev]' "$NUMPY_PIN"
  touch "$stamp"
fi
VENV_NUMPY=$(.venv/bin/python -c "import numpy; print(numpy.__version__)") || {
  echo "setup: .venv cannot import numpy (see above)" >&2; exit 1; }
if [ "${VENV_NUMPY%%.*}" != "$SYS_NUMPY_MAJOR" ]; then
  cat >&2 <<MSG
setup: .venv has NumPy $VENV_NUMPY but the system's OpenVDB module is built against NumPy $SYS_NUMPY;
  they must share the major version. Fix: .venv/bin/python -m pip install '$NUMPY_PIN'
MSG
  exit 1
fi
.venv/bin/python -c "import numpy, pipeline, cc3d  # cc3d: connected-components-3d from .[dev] (bench anchor)
try:
    import openvdb as vdb
except ImportError:
    import pyopenvdb as vdb
" || { echo "setup: the environment does not import (see above)" >&2; exit 1; }
.venv/bin/python -c "from pipeline.io import _leafbuild" 2>/dev/null || echo "setup: warning: the compiled leaf \
builder (pipeline/io/leafbuild.cpp) was not built; grids are written with pyopenvdb's copyFromArray (slower)" >&2
