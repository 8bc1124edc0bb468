#!/usr/bin/env bash
# The whole test suite, on a fresh machine as on a developer's: what the tests need is
# installed where it is missing (as root; otherwise the exact command is printed and the
# script stops), then every cargo test binary runs (one failure does not hide the rest), the
# integration tests again on PostgreSQL, then the Python checks of the running service, with
# the lint (.ci/lint) beside them. Each step says when it starts; the last line says which
# steps failed. Exit status 1 on any failure.
#
# usage: ./test.sh            (CI runs exactly this, after its quick checks: .ci/run)
# docs/testing.md says what each step checks and what it needs.
set -euo pipefail
cd "$(dirname "$0")"
export CARGO_TERM_COLOR="${CARGO_TERM_COLOR:-never}"
step() { echo "[test.sh ${SECONDS}s] $*"; }

# --- What the tests need -------------------------------------------------------------------

# The Python checks' packages, pinned (tests/python/requirements.txt).
requirements=tests/python/requirements.txt
# The requirements not met by the python3 on the PATH, one a line (empty when all are).
missing_python() {
    python3 - "$requirements" <<'EOF'
import importlib.metadata as md, re, sys
def key(v):
    return tuple(int(x) if x.isdigit() else 0 for x in re.split(r"[.+-]", v)[:3])
for line in open(sys.argv[1]):
    req = line.split("#")[0].strip()
    if not req:
        continue
    name, op, want = re.match(r"([A-Za-z0-9_.-]+)\s*(==|>=)?\s*(\S*)", req).groups()
    try:
        have = md.version(name)
    except md.PackageNotFoundError:
        print(req)
        continue
    if (op == "==" and have != want) or (op == ">=" and key(have) < key(want)):
        print(req)
EOF
}

# The Debian packages the tests need (installed with the packages they recommend: Chromium's
# fonts among them, for the dashboard's screenshots).
apt_missing=()
# The dashboard's browser test drives /usr/bin/chromium through /usr/bin/chromedriver.
[ -x /usr/bin/chromium ] || apt_missing+=(chromium)
[ -x /usr/bin/chromedriver ] || apt_missing+=(chromium-driver)
# The store tests and the PostgreSQL re-run start a throwaway server (initdb, postgres).
if ! command -v initdb >/dev/null && ! ls /usr/lib/postgresql/*/bin/initdb >/dev/null 2>&1; then
    apt_missing+=(postgresql)
fi
# The ISO programs are run through LinuxCNC's own interpreter (rs274); the loop with a real
# control runs LinuxCNC's simulation with a truth component built by halcompile (-dev).
[ -x /usr/bin/rs274 ] || apt_missing+=(linuxcnc-uspace)
[ -x /usr/bin/halcompile ] || apt_missing+=(linuxcnc-uspace-dev)
# As root the loop runs each family in namespaces of its own, bringing their loopback up (ip).
if [ "$(id -u)" -eq 0 ] && ! command -v ip >/dev/null; then
    apt_missing+=(iproute2)
fi
if ! command -v python3 >/dev/null; then
    apt_missing+=(python3 python3-pip)
elif ! python3 -m pip --version >/dev/null 2>&1; then
    apt_missing+=(python3-pip)
fi
apt_cmd="apt-get update && apt-get install -y ${apt_missing[*]:-}"
# A Python whose packages the system manages (PEP 668: Debian's own python3, outside a
# virtual environment) takes pip's packages only with --break-system-packages.
pip_cmd() {
    local flags=(--quiet --disable-pip-version-check)
    if python3 -c 'import os, sys, sysconfig; sys.exit(sys.prefix != sys.base_prefix or not os.path.exists(os.path.join(sysconfig.get_path("stdlib"), "EXTERNALLY-MANAGED")))' 2>/dev/null; then
        flags+=(--break-system-packages)
    fi
    echo "python3 -m pip install ${flags[*]} -r $requirements"
}

if python3 -m pip --version >/dev/null 2>&1; then
    py_missing="$(missing_python)"
else
    # Without python3 and pip every Python package is missing too.
    py_missing="$(grep -v '^ *#' "$requirements" | grep .)"
fi
if [[ "$(id -u)" -ne 0 && ( "${#apt_missing[@]}" -gt 0 || -n "$py_missing" ) ]]; then
    echo "test.sh: the tests need what is missing here; install it as root, then run again:"
    if [ "${#apt_missing[@]}" -gt 0 ]; then
        echo "    $apt_cmd"
    fi
    if [ -n "$py_missing" ]; then
        echo "    $(pip_cmd)    # missing: $(echo $py_missing)"
    fi
    exit 1
fi
if [ "${#apt_missing[@]}" -gt 0 ]; then
    step "installing Debian packages: ${apt_missing[*]}"
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq >/dev/null
    apt-get install -y -qq "${apt_missing[@]}" >/dev/null
    py_missing="$(missing_python)"
fi
if [ -n "$py_missing" ]; then
    step "installing Python packages: $(echo $py_missing)"
    $(pip_cmd)
    py_missing="$(missing_python)"
    if [ -n "$py_missing" ]; then
        echo "test.sh: pip left these unmet: $(echo $py_missing)"
        exit 1
    fi
fi

# --- The tests -----------------------------------------------------------------------------

# Each step runs whatever the previous ones gave; a failed one is named at the end.
failed=()
steps=0
check() {
    local name="$1"
    shift
    steps=$((steps + 1))
    step "$name"
    if ! "$@"; then
        failed+=("$name")
        echo "[test.sh ${SECONDS}s] FAILED: $name"
    fi
}
# A step that mostly waits on the wall clock runs beside the next ones: its output goes to a
# file, shown (and its result counted) by finish_background before the last line.
background=()
in_background() {
    local name="$1"
    shift
    steps=$((steps + 1))
    step "$name (in the background; its output when it ends)"
    local log="$out/background-${#background[@]}.log"
    "$@" >"$log" 2>&1 &
    background+=("$!|$log|$name")
}
finish_background() {
    local b pid log name
    for b in "${background[@]}"; do
        IFS='|' read -r pid log name <<<"$b"
        step "$name (the background step)"
        if wait "$pid"; then
            cat "$log"
        else
            cat "$log"
            failed+=("$name")
            echo "[test.sh ${SECONDS}s] FAILED: $name"
        fi
    done
}

out="$(mktemp -d)"
target="${CARGO_TARGET_DIR:-target}"
not_run=()
# LinuxCNC runs the measurement program, the gateway writes the served sets into its
# kinematics and the tool tip is measured, on both trt families at once, with the faults (about
# 5 min of machine motion on the wall clock, little CPU): it starts as soon as the service's binary
# is built, beside the rest of the build and everything after it (started after the whole
# build, it was the last step to end). It runs its own copy of the binary, which nothing
# rebuilds under it. It runs LinuxCNC as a non-root user and installs the truth component, so
# it needs root. The binary is built as the integration tests build it, with the features
# the test build gives the dependencies (the root's and the service's dev-dependencies: tokio's
# test clock, the browser test's client): a plain `cargo build` resolved them without, and the
# test build after it compiled some 110 crates again (227 s of CI's 1254). Every unit this
# builds is one the whole test build needs (`cargo test --unit-graph` shows the same units).
if [ "$(id -u)" -eq 0 ]; then
    step "build the service's binary and the integration tests (for LinuxCNC in the loop)"
    cargo test --locked --no-run -p driftwatch -p driftwatch-service --test it
    cp "$target/debug/driftwatch" "$out/driftwatch"
    chmod o+x "$out"  # LinuxCNC's user works in $out/linuxcnc
    in_background "LinuxCNC in the loop (tests/linuxcnc/loop.py)" \
        python3 tests/linuxcnc/loop.py "$out/driftwatch" "$out/linuxcnc"
else
    not_run+=("LinuxCNC in the loop (needs root: a user for LinuxCNC, the truth component)")
fi

# Build every test binary: a build error stops here, and a failing test further on still
# leaves the driftwatch binary the Python checks run fresh.
step "build the tests"
cargo test --locked --no-run
# The binary `cargo test` built for the command-line tests.
bin="$target/debug/driftwatch"
check "cargo test (every test binary)" cargo test --locked --no-fail-fast
# The modules of the integration tests (tests/it, one binary) that take their store from
# tests/it/common run again on PostgreSQL, chosen by their module paths (the fault injection of
# tests/it/service.rs uses SQLite triggers and the crash test reads the SQLite file: they stay
# on SQLite; the fleet test is PostgreSQL's own).
check "integration tests on PostgreSQL" env DRIFTWATCH_TEST_BACKEND=postgres \
    cargo test --locked --no-fail-fast --test it -- api:: daemon:: nc_offsets:: nc_push:: \
    opcua:: verification::
# The lint (.ci/lint: clippy on every target, the service without its simulator, each pure
# crate alone) needs no test: it runs beside the Python checks, on what the cores leave over
# (nice 19), in the tests' target directory, whose build scripts and procedural macros it
# reuses, once the last cargo command above has ended (two on one directory wait on its lock).
# In a directory of its own it built all of those again: clippy alone took 5 min instead of
# about 1.5. Beside the first build it had slowed that by a third.
in_background "lint (.ci/lint)" nice -n 19 .ci/lint

# An independent reader (the `mcap` package) checks a simulated recording against the contract.
check "simulate and check a recording" bash -c \
    "'$bin' simulate --scenario patent --out '$out/patent.mcap' \
     && python3 tests/python/check_recording.py '$out/patent.mcap' 15 24"
# A second, independent writer of the contract: fresh recordings of every conformance case
# (other seeds than the committed ones in tests/data/conformance), solved and diagnosed.
check "conformance (independent writer)" \
    python3 tests/python/check_conformance.py "$bin" "$out/conformance" --seed 7 --cycles 3
# Four hours of the default plant day at 600x (about 25 s), then its recordings.
check "serve 4 h at 600x and check its files" bash -c \
    "RUST_LOG=warn '$bin' serve --time-scale 600 --until 240 --data-dir '$out/serve' \
       --listen 127.0.0.1:0 && python3 tests/python/check_daemon_files.py '$out/serve/mcap/sim-1'"
# kill -9 at random moments, mid-cycle included, on both links (32 trials, three at a time,
# about 30 s): no validated result lost, no version going back, every recording readable.
check "kill harness" python3 tests/python/kill_harness.py "$bin" "$out/kill" --sim 16 --nc 16
# The served OpenAPI document, checked by an independent validator.
check "OpenAPI document (openapi-spec-validator)" \
    python3 tests/python/check_openapi.py "$bin" "$out/openapi"
# A client generated from that document drives the NC handshake to a validated set. Its NC
# spends the cycle's minute on the wall clock (as a real one) mostly asleep, so it runs beside
# the steps after it (Schemathesis, the soak, the full disk).
in_background "NC handshake through a generated client (openapi-python-client)" \
    python3 tests/python/generated_client.py "$bin" "$out/client"
# Schemathesis on every operation (150 examples each with a token, about 40 s): no 5xx, no
# answer that breaks the document.
check "schemathesis" \
    python3 tests/python/schemathesis_run.py "$bin" "$out/schemathesis" --max-examples 150
# 300 000 stray and 30 clock-skewed NC events: memory and storage flat.
check "NC soak" python3 tests/python/soak_nc.py "$bin" "$out/soak"
# A real full disk under the running service (a small tmpfs, so it needs root to mount): the
# NC is served only what the store holds, the fault is reported, and the service recovers by
# itself when the disk has room again, and after a restart.
if [ "$(id -u)" -eq 0 ]; then
    check "full disk while serving (a small tmpfs)" \
        python3 tests/python/full_disk.py "$bin" "$out/full-disk" --seconds 20
    check "full disk from the start (a small tmpfs)" \
        python3 tests/python/full_disk.py "$bin" "$out/full-disk-start" --seconds 20 \
        --start-full-kib 500
else
    not_run+=("full disk (needs root to mount a small filesystem)")
fi
finish_background

if [ "${#failed[@]}" -gt 0 ]; then
    echo "test.sh: FAILED ${#failed[@]} of $steps steps in ${SECONDS} s: $(IFS=';'; echo "${failed[*]}") (files in $out)"
    exit 1
fi
rm -rf "$out"
if [ "${#not_run[@]}" -gt 0 ]; then
    echo "test.sh: all $steps steps passed in ${SECONDS} s; not run: $(IFS=';'; echo "${not_run[*]}")"
else
    echo "test.sh: all $steps steps passed in ${SECONDS} s"
fi
