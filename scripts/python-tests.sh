#!/usr/bin/env bash
# Builds the Python package (python/) from source into a fresh virtual environment and
# runs its tests. Used by CI; runs anywhere with cargo and python3 (as root on Debian it
# installs python3 and python3-venv when they are missing).
#
#   scripts/python-tests.sh [pytest arguments…]
#
# Environment: STICKSLIP_PYTHON_VENV (default target/python-venv), STICKSLIP_PYTHON_TARGET
# (cargo's target directory for the extension, default target/python). GPU tests use the
# GPU when an adapter exists; with STICKSLIP_REQUIRE_GPU=1 a missing adapter fails them.
set -euo pipefail
cd "$(dirname "$0")/.."
root=$PWD
venv=${STICKSLIP_PYTHON_VENV:-$root/target/python-venv}
export CARGO_TARGET_DIR=${STICKSLIP_PYTHON_TARGET:-$root/target/python}

install() {
    if [ "$(id -u)" = 0 ] && command -v apt-get > /dev/null; then
        echo "python-tests: installing $*"
        export DEBIAN_FRONTEND=noninteractive
        apt-get update
        apt-get install -y --no-install-recommends "$@"
    else
        echo "python-tests: missing $* (install them, or run as root on Debian)" >&2
        exit 1
    fi
}
command -v python3 > /dev/null || install python3 python3-venv
mkdir -p "$root/target"
rm -rf "$venv"
# Debian's python3 has venv but not the ensurepip it needs: python3-venv adds it.
if ! python3 -m venv "$venv" > "$root/target/python-venv.log" 2>&1; then
    cat "$root/target/python-venv.log" >&2
    rm -rf "$venv"
    install python3-venv
    python3 -m venv "$venv"
fi
py=$venv/bin/python
# The maturin build backend runs the maturin executable: the environment's, on PATH.
export PATH="$venv/bin:$PATH"
echo "python-tests: $($py --version) in $venv"
"$py" -m pip install --quiet --upgrade pip
"$py" -m pip install --quiet "maturin>=1.9.4,<2" numpy scipy pytest
# From source, with cargo (release build of the extension; the long part).
echo "python-tests: pip install ./python (cargo target $CARGO_TARGET_DIR)"
start=$(date +%s)
"$py" -m pip install --no-build-isolation ./python
echo "python-tests: built and installed in $(( $(date +%s) - start )) s"

# From the repository root with importlib mode: the installed package is tested, not
# python/stickslip (which has no compiled module).
set +e
"$venv/bin/pytest" --import-mode=importlib -ra python/tests "$@"
rc=$?
set -e
if [ $rc -eq 5 ]; then
    echo "python-tests: no tests were collected" >&2
    exit 1
fi
exit $rc
