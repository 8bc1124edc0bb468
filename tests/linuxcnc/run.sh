#!/bin/sh
# Run driftwatch's ISO measurement program on a headless LinuxCNC 2.9 (uspace) simulator of
# xyzbc-trt (xyzbc-trt-kins) or xyzac-trt, with the truth component dwtruth on the probe input
# (installed first: halcompile --install tests/linuxcnc/dwtruth.comp, as root).
# Usage: [MACHINE=xyzbc-trt|xyzac-trt] tests/linuxcnc/run.sh [driftwatch binary] [work dir]
# As root it runs LinuxCNC as the user $LCNC_USER (default lcnc; created if missing),
# since rtapi_app refuses to run as root.
set -eu
HERE=$(cd "$(dirname "$0")" && pwd)
DW=${1:-$HERE/../../target/release/driftwatch}
WORK=${2:-$(mktemp -d /tmp/dw-lcnc.XXXXXX)}
RUN_USER=${LCNC_USER:-lcnc}
MACHINE=${MACHINE:-xyzbc-trt}
case $MACHINE in
    xyzbc-trt|xyzac-trt) INI=$MACHINE.ini ;;
    *) echo "MACHINE: xyzbc-trt or xyzac-trt" >&2; exit 2 ;;
esac

mkdir -p "$WORK"
cp -r "$HERE/$INI" "$HERE"/sim.hal "$HERE"/bc.hal "$HERE"/ac.hal "$HERE"/sim.tbl \
      "$HERE"/display.py "$WORK"/
"$DW" nc program --machine "$HERE/../../deploy/linuxcnc/machines/$MACHINE.toml" --dialect iso \
    --out "$WORK/$MACHINE.ngc"

as_user() { "$@"; }
if [ "$(id -u)" = 0 ]; then
    id "$RUN_USER" >/dev/null 2>&1 || useradd -m "$RUN_USER"
    chown -R "$RUN_USER" "$WORK"
    as_user() { runuser -u "$RUN_USER" -- "$@"; }
fi

T0=$(date +%s.%N)
cd "$WORK"
status=0
as_user env -u DISPLAY DW_T0="$T0" DW_PROGRAM="$WORK/$MACHINE.ngc" DW_OUT="$WORK/results.json" \
    DW_REPEAT="${DW_REPEAT:-20}" PATH=/usr/bin:/bin \
    linuxcnc -r "$WORK/$INI" >"$WORK/linuxcnc.out" 2>&1 || status=$?
T1=$(date +%s.%N)
# nothing of this instance may stay behind
as_user halrun -U >/dev/null 2>&1 || true

echo "work dir: $WORK (linuxcnc exit status $status)"
/usr/bin/python3 - "$WORK" "$T0" "$T1" <<'PY'
import json, sys
work, t0, t1 = sys.argv[1], float(sys.argv[2]), float(sys.argv[3])
r = json.load(open(work + "/results.json"))
print("wall s: task up %.2f, homed %.2f (homing %.3f), display exit %.2f, linuxcnc exit %.2f (shutdown %.2f)" % (
    r.get("t_task_up_s", -1), r.get("t_ready_s", -1), r.get("t_home_s", -1),
    r.get("t_display_exit_s", -1), t1 - t0, t1 - t0 - r.get("t_display_exit_s", 0)))
for k in ("overshoot_um_z", "overshoot_um_y", "g38_wall_s", "beam_trips", "tcp_demo", "switchkins_after_M428",
          "switchkins_after_M429", "x_rot_point_set_while_running", "program_s", "program_errors"):
    print(k, r.get(k))
print("probe positions seen during the program:", len(r.get("program_probed_positions", [])))
PY
echo "--- program LOG file"
cat "$WORK"/dw9100_*.log 2>/dev/null || echo "(no LOG file)"
