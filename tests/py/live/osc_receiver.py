# Receive VMC bundles for `seconds` with python-osc and check every message.
import json, socket, sys, time, math
from pythonosc.osc_bundle import OscBundle
from pythonosc.osc_message import OscMessage
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
s.bind(("127.0.0.1", int(sys.argv[1])))
s.settimeout(0.5)
print("ready", flush=True)
end = time.time() + float(sys.argv[2])
times, names, bad, bones = [], set(), 0, 0
while time.time() < end:
    try:
        data = s.recv(65536)
    except socket.timeout:
        continue
    times.append(time.time())
    b = OscBundle(data)
    addrs = [m.address for m in b]
    if "/VMC/Ext/OK" not in addrs or "/VMC/Ext/T" not in addrs or "/VMC/Ext/Root/Pos" not in addrs:
        bad += 1
    for m in b:
        if m.address == "/VMC/Ext/Bone/Pos":
            p = m.params
            if len(p) != 8 or not isinstance(p[0], str) or not all(isinstance(v, float) for v in p[1:]):
                bad += 1
                continue
            if abs(math.sqrt(sum(v * v for v in p[4:])) - 1.0) > 1e-3:
                bad += 1
            names.add(p[0]); bones += 1
span = times[-1] - times[0] if len(times) > 1 else 0.0
print(json.dumps({"bundles": len(times), "rate": (len(times) - 1) / span if span else 0.0,
                  "names": sorted(names), "bad": bad, "bones": bones}))
