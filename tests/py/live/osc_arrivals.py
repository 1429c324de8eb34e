# Receive VMC bundles for `seconds`, each with the kernel's arrival timestamp (SO_TIMESTAMPNS,
# socket(7): so the receiver's own scheduling on a busy machine does not move it); prints
# `[[arrival_s, T], ...]` where T is the bundle's `/VMC/Ext/T` (the frame's time).
import json, socket, struct, sys, time
from pythonosc.osc_bundle import OscBundle
SO_TIMESTAMPNS = 35  # asm-generic/socket.h; Python's socket module does not name it
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
s.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
s.bind(("127.0.0.1", int(sys.argv[1])))
s.settimeout(0.5)
print("ready", flush=True)
end = time.monotonic() + float(sys.argv[2])
got = []
while time.monotonic() < end:
    try:
        data, anc, _, _ = s.recvmsg(65536, 64)
    except socket.timeout:
        continue
    stamp = [struct.unpack("qq", d[:16]) for lvl, typ, d in anc if typ == SO_TIMESTAMPNS]
    got.append((stamp[0][0] + stamp[0][1] * 1e-9, data))
out = []
for t, data in got:
    ts = [m.params[0] for m in OscBundle(data) if m.address == "/VMC/Ext/T"]
    out.append([t, ts[0] if ts else -1.0])
print(json.dumps(out))
