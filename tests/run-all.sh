#!/usr/bin/env bash
# Runs every test of cooploc, after installing what the tests need beyond cargo:
# a Python virtualenv (.venv) with the pinned reference tools of tests/requirements.txt,
# the MAVProxy module of tools/mavproxy linked into it, Debian's headless Chromium, and iproute2
# (network namespaces, tc) for tests/netns.rs.
# Usage (from anywhere): bash tests/run-all.sh
set -euo pipefail
cd "$(dirname "$0")/.."

venv=.venv
stamp=$venv/.requirements.sha256
want=$(sha256sum tests/requirements.txt | cut -d' ' -f1)
if [ ! -x "$venv/bin/python" ] || [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
    echo "==> creating $venv with tests/requirements.txt"
    rm -rf "$venv"
    python3 -m venv "$venv"
    "$venv/bin/pip" install --quiet --disable-pip-version-check -r tests/requirements.txt
    echo "$want" > "$stamp"
fi
export COOPLOC_PYTHON="$PWD/$venv/bin/python"

# The cooploc Python package (python/: PyO3, built by maturin), installed editable into the
# virtualenv: `import cooploc`, and MAVProxy's `module load cooploc` (the MAVProxy module is
# cooploc.mavproxy). A link that an older checkout left in MAVProxy's modules would be loaded
# first: it goes.
echo "==> building the cooploc Python package (maturin develop --release)"
VIRTUAL_ENV="$PWD/$venv" "$venv/bin/maturin" develop --release --quiet -m python/Cargo.toml
# Its crate is not a default member of the workspace, so .ci/run's clippy does not see it.
echo "==> cargo clippy -p cooploc-py --all-targets -- -D warnings"
cargo clippy --quiet -p cooploc-py --all-targets -- -D warnings
mavproxy_modules=$("$COOPLOC_PYTHON" -c 'import MAVProxy.modules, os; print(os.path.dirname(MAVProxy.modules.__file__))')
rm -f "$mavproxy_modules/mavproxy_cooploc.py"

# Headless Chromium for the ground station's browser test (tests/gcs.rs), from Debian's packages.
if ! command -v chromium > /dev/null 2>&1 && ! command -v chromium-browser > /dev/null 2>&1; then
    echo "==> installing chromium (the ground station's browser test)"
    sudo=""
    [ "$(id -u)" = 0 ] || sudo="sudo"
    { $sudo apt-get update -qq && $sudo env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium > /dev/null; } \
        || echo "could not install chromium: the browser test fails under CI=true and skips elsewhere"
fi

# iproute2 (ip, tc) for the network-namespace test (tests/netns.rs), from Debian's packages.
if ! command -v ip > /dev/null 2>&1 || ! command -v tc > /dev/null 2>&1; then
    echo "==> installing iproute2 (the network-namespace test)"
    sudo=""
    [ "$(id -u)" = 0 ] || sudo="sudo"
    { $sudo apt-get update -qq && $sudo env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq iproute2 > /dev/null; } \
        || echo "could not install iproute2: the namespace test fails under CI=true and skips elsewhere"
fi

echo "==> validating dialects/cooploc.xml with pymavlink's mavgen (wire protocol 2.0)"
mavgen_out=$(mktemp -d)
"$COOPLOC_PYTHON" -m pymavlink.tools.mavgen --lang=Python3 --wire-protocol=2.0 \
    --output="$mavgen_out/cooploc.py" dialects/cooploc.xml > "$mavgen_out/log" 2>&1 \
    || { cat "$mavgen_out/log"; echo "mavgen rejected dialects/cooploc.xml"; exit 1; }
rm -rf "$mavgen_out"

# One optimised build serves the unit, property, Monte Carlo and end-to-end tests.
echo "==> cargo test --release"
cargo test --release --all-targets
echo "==> doc tests"
cargo test --release --doc
