"""The OpenAPI document a running driftwatch serves, checked by an independent validator
(`openapi-spec-validator`).

usage: python3 check_openapi.py BINARY OUTDIR

Starts `BINARY serve` (the shipped default, 600x time, data in OUTDIR/data, a free loopback
port), reads GET /api/v1/openapi.json, stops the service and validates the document against
its OpenAPI version's specification with openapi-spec-validator: the document's structure,
every schema, and every `$ref` resolved (a reference to a schema the document does not define
is an error: generators drop the operations that use it). The document is kept as
OUTDIR/openapi.json. Prints each error and closes with
  openapi: VERSION, P paths, S schemas, E errors (openapi-spec-validator X.Y.Z)
The exit status is 1 on any error (or when the service did not serve the document), else 0.
"""
from __future__ import annotations

import argparse
import importlib.metadata
import json
import os
import shutil
import subprocess
import sys
import urllib.request

from served import stop, wait_served


def fetch_document(binary: str, outdir: str) -> dict:
    """The document as a freshly started `serve` answers it."""
    log_path = os.path.join(outdir, "service.log")
    with open(log_path, "wb") as log:
        proc = subprocess.Popen(
            [binary, "serve", "--time-scale", "600", "--until", "100000",
             "--data-dir", os.path.join(outdir, "data"), "--listen", "127.0.0.1:0"],
            env=dict(os.environ, RUST_LOG="warn"), stdout=log, stderr=subprocess.STDOUT)
    try:
        base = wait_served(proc, log_path)
        if base is None:
            sys.exit(f"openapi: the service did not say where it listens (see {log_path})")
        with urllib.request.urlopen(base + "/api/v1/openapi.json", timeout=30) as r:
            return json.load(r)
    finally:
        stop(proc)


def describe(err: BaseException) -> str:
    """One line per error: the validator's own message, or for a reference that resolves
    to nothing the reference alone (its exception quotes the whole document)."""
    ref = getattr(err, "ref", None)
    if ref is not None:
        return f"{ref!r} does not exist in the document"
    path = "/".join(str(p) for p in getattr(err, "absolute_path", []) or [])
    msg = getattr(err, "message", None) or str(err)
    return (f"at {path}: " if path else "") + msg.splitlines()[0][:300]


def validate(doc: dict) -> list[str]:
    """Every error the validator finds; an exception that stops it (an unresolvable
    reference does) is an error too."""
    from openapi_spec_validator import OpenAPIV30SpecValidator, OpenAPIV31SpecValidator
    version = str(doc.get("openapi", ""))
    if version.startswith("3.1"):
        validator = OpenAPIV31SpecValidator(doc)
    elif version.startswith("3.0"):
        validator = OpenAPIV30SpecValidator(doc)
    else:
        return [f"openapi version {version!r} is not 3.0 or 3.1"]
    errors = []
    try:
        for err in validator.iter_errors():
            errors.append(describe(err))
    except Exception as err:  # the validator stops at an error it cannot step over
        errors.append(describe(err))
    return errors


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("binary")
    ap.add_argument("outdir")
    a = ap.parse_args()
    outdir = os.path.abspath(a.outdir)
    shutil.rmtree(outdir, ignore_errors=True)
    os.makedirs(outdir)
    doc = fetch_document(os.path.abspath(a.binary), outdir)
    with open(os.path.join(outdir, "openapi.json"), "w") as f:
        json.dump(doc, f, indent=2)
    errors = validate(doc)
    for e in errors:
        print(f"openapi error: {e}")
    paths = len(doc.get("paths") or {})
    schemas = len((doc.get("components") or {}).get("schemas") or {})
    tool = importlib.metadata.version("openapi-spec-validator")
    print(f"openapi: {doc.get('openapi')}, {paths} paths, {schemas} schemas, "
          f"{len(errors)} errors (openapi-spec-validator {tool})")
    return 1 if errors else 0


if __name__ == "__main__":
    sys.exit(main())
