#!/usr/bin/python3
"""Drive a running LinuxCNC from a separate process (what a gateway does): run a G-code file
in AUTO and print the task's error messages. Run it as the user LinuxCNC runs as: the NML
shared memory is that user's (mode 600/700); as root the linuxcnc module's stat.poll()
fails ("tool mmap not available", SystemError).

Usage: drive.py program.ngc
"""
import sys
import time

import linuxcnc

s = linuxcnc.stat()
c = linuxcnc.command()
e = linuxcnc.error_channel()
s.poll()
if s.task_state != linuxcnc.STATE_ON or not all(s.homed[:5]):
    sys.exit("machine not on and homed")
c.mode(linuxcnc.MODE_AUTO)
c.wait_complete()
c.program_open(sys.argv[1])
c.wait_complete()
t = time.time()
c.auto(linuxcnc.AUTO_RUN, 0)
c.wait_complete()
time.sleep(0.5)
errors = 0
while True:
    s.poll()
    m = e.poll()
    if m:
        print("task:", m[1], flush=True)
        errors += m[0] in (linuxcnc.NML_ERROR, linuxcnc.OPERATOR_ERROR)
    if s.interp_state == linuxcnc.INTERP_IDLE:
        break
    time.sleep(0.05)
print("program ended in %.1f s, %d errors, last probe %s" % (
    time.time() - t, errors, s.probed_position[:5]))
sys.exit(1 if errors else 0)
