#!/usr/bin/env python3
"""A simulated machine tool as an OPC UA server (the `asyncua` package), for the OPC UA link's
test. It implements driftwatch's node contract (docs/integrate-nc.md, "The OPC UA link", "The
node contract") from the documents alone, with no driftwatch code:

- publishes the spindle speed (Double), the active program's state (LocalizedText, OPC 40501
  values Running / Ended) and two temperatures (Double), changing a little every second;
- when `Driftwatch/CycleRequest` holds an order it has not run, runs it: the program state
  goes to Running, the spindle to the order's speed, and each step's latched position is
  appended to `Driftwatch/Detections` as {"t_ns", "msg"} with the order's cycle number and
  this machine's clock; then the state goes back to Ended;
- keeps what driftwatch writes to the compensation nodes.

The latched positions come from a file (`--detections`: a JSON list of /probe/detection
messages, one per step label), written by the test from driftwatch's truth simulator before
the server starts: the server plays back a machine's readings, it does not compute them.

A report (`--report`, JSON, rewritten atomically every 0.2 s and at each approach) says what
the server saw: cycles begun, the one running and its approaches done, the compensation values and version written to it.
"""

import argparse
import asyncio
import json
import math
import os
import time

from asyncua import Server, ua

NS_URI = "urn:driftwatch:test-machine"


async def variable(parent, idx, path, value, vtype, writable=False):
    node = await parent.add_variable(
        ua.NodeId(path, idx), ua.QualifiedName(path.split("/")[-1], idx), value, varianttype=vtype
    )
    if writable:
        await node.set_writable()
    return node


def write_report(path, report):
    tmp = path + ".tmp"
    with open(tmp, "w") as f:
        json.dump(report, f)
    os.replace(tmp, path)


async def security(server, args):
    if args.security == "none":
        server.set_security_policy([ua.SecurityPolicyType.NoSecurity])
        return
    # A server certificate of its own, made for this run (the `cryptography` package comes
    # with asyncua).
    import datetime
    import ipaddress

    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import rsa
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    key = rsa.generate_private_key(public_exponent=65537, key_size=2048)
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "driftwatch test machine")])
    now = datetime.datetime.now(datetime.timezone.utc)
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(days=1))
        .not_valid_after(now + datetime.timedelta(days=30))
        .add_extension(
            x509.SubjectAlternativeName(
                [
                    x509.UniformResourceIdentifier(args.app_uri),
                    x509.DNSName("localhost"),
                    # The client checks the host it dialled against the certificate.
                    x509.IPAddress(ipaddress.ip_address("127.0.0.1")),
                ]
            ),
            critical=False,
        )
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True,
                content_commitment=True,
                key_encipherment=True,
                data_encipherment=True,
                key_agreement=False,
                key_cert_sign=False,
                crl_sign=False,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .add_extension(
            x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
            critical=False,
        )
        .sign(key, hashes.SHA256())
    )
    cert_path = os.path.join(args.workdir, "server_cert.der")
    key_path = os.path.join(args.workdir, "server_key.pem")
    with open(cert_path, "wb") as f:
        f.write(cert.public_bytes(serialization.Encoding.DER))
    with open(key_path, "wb") as f:
        f.write(
            key.private_bytes(
                serialization.Encoding.PEM,
                serialization.PrivateFormat.TraditionalOpenSSL,
                serialization.NoEncryption(),
            )
        )
    await server.load_certificate(cert_path)
    await server.load_private_key(key_path)
    server.set_security_policy([ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt])


async def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--port", type=int, required=True)
    ap.add_argument("--rpm", type=float, default=20000.0, help="spindle speed while idle")
    ap.add_argument("--detections", required=True, help="JSON list of detection messages")
    ap.add_argument("--report", required=True)
    ap.add_argument("--workdir", required=True)
    ap.add_argument("--security", choices=["none", "sign_and_encrypt"], default="none")
    ap.add_argument("--app-uri", default="urn:driftwatch:test-machine:server")
    ap.add_argument("--step-s", type=float, default=0.15, help="machine time of one approach")
    args = ap.parse_args()

    with open(args.detections) as f:
        readings = json.load(f)
    by_label = {d["step"]: d for d in readings}

    server = Server()
    await server.init()
    server.set_endpoint(f"opc.tcp://127.0.0.1:{args.port}/driftwatch/")
    server.set_server_name("driftwatch test machine")
    await server.set_application_uri(args.app_uri)
    await security(server, args)
    idx = await server.register_namespace(NS_URI)
    m = await server.nodes.objects.add_object(ua.NodeId("Machine", idx), ua.QualifiedName("Machine", idx))
    D, S, L, I = ua.VariantType.Double, ua.VariantType.String, ua.VariantType.LocalizedText, ua.VariantType.Int64
    spindle = await variable(m, idx, "CncInterface/CncSpindleList/Spindle/ActSpeed", args.rpm, D)
    state = await variable(m, idx, "Production/ActiveProgram/State/CurrentState", ua.LocalizedText("Ended"), L)
    temps = {
        "spindle_housing": await variable(m, idx, "Monitoring/Temperature/SpindleHousing", 24.0, D),
        "ambient": await variable(m, idx, "Monitoring/Temperature/Ambient", 20.0, D),
    }
    request = await variable(m, idx, "Driftwatch/CycleRequest", "", S, writable=True)
    detections = await variable(m, idx, "Driftwatch/Detections", "", S)
    comp_names = ["B_pivot_x_um", "B_pivot_z_um", "C_pivot_x_um", "C_pivot_y_um", "C_tilt_a_urad", "C_tilt_b_urad"]
    comp = {n: await variable(m, idx, f"Driftwatch/Compensation/{n}", 0.0, D, writable=True) for n in comp_names}
    version = await variable(m, idx, "Driftwatch/Compensation/version", 0, I, writable=True)

    report = {
        "cycles_run": [],
        "running": None,
        "compensation": {},
        "version": 0,
        "requests": 0,
        "rpm": args.rpm,
    }
    ran = set()
    t_start = time.time()
    async with server:
        last_report = 0.0
        while True:
            now = time.time()
            # The machine's own slow drift: the temperatures move, the spindle holds.
            await temps["spindle_housing"].write_value(24.0 + 2.0 * math.sin((now - t_start) / 60.0))
            await temps["ambient"].write_value(20.0 + 0.1 * math.sin((now - t_start) / 30.0))
            text = await request.read_value()
            if text:
                report["requests"] += 1
                order = json.loads(text)
                if order["cycle"] not in ran:
                    ran.add(order["cycle"])
                    # Listed as begun: driftwatch may close the cycle at its last approach,
                    # before the program's end.
                    report["cycles_run"].append(order["cycle"])
                    await run_cycle(order, by_label, spindle, state, detections, args, report)
            if now - last_report > 0.2:
                report["compensation"] = {n: await comp[n].read_value() for n in comp_names}
                report["version"] = await version.read_value()
                write_report(args.report, report)
                last_report = now
            await asyncio.sleep(0.05)


async def run_cycle(order, by_label, spindle, state, detections, args, report):
    """The measurement program: each step's latched position appended as it trips (the
    report says how far it got, so that a test can kill the server in the middle)."""
    await spindle.write_value(float(order["spindle_rpm"]))
    await state.write_value(ua.LocalizedText("Running"))
    doc = {"cycle": order["cycle"], "detections": []}
    await detections.write_value(json.dumps(doc))
    for step in order["steps"]:
        await asyncio.sleep(args.step_s)
        reading = dict(by_label[step["step"]])
        reading["cycle"] = order["cycle"]
        doc["detections"].append({"t_ns": time.time_ns(), "msg": reading})
        await detections.write_value(json.dumps(doc))
        report["running"] = {"cycle": order["cycle"], "done": len(doc["detections"])}
        write_report(args.report, report)
    report["running"] = None
    await asyncio.sleep(args.step_s)
    await state.write_value(ua.LocalizedText("Ended"))
    await spindle.write_value(args.rpm)


if __name__ == "__main__":
    asyncio.run(main())
