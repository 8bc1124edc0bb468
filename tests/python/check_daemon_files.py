"""Check the MCAP files `driftwatch serve` leaves in a machine's recording directory with the
`mcap` Python package (an independent reader).

usage: python3 check_daemon_files.py [--short] DIR
       python3 check_daemon_files.py --partial FILE.mcap.partial

DIR mode reads every `*.mcap` in DIR (the closed files, including those recovered after a
crash) with CRC validation and checks: each file is finished (has a summary); every channel
uses message encoding json and a jsonschema object schema; the files together hold the
contract topics (not with --short: a run stopped before its first cycle has none of the
cycle topics); log times never go back within a channel of a file; every message is JSON
and valid against its channel's schema (the `jsonschema` package);
every /cycle/result is unique and its cycle's /probe/detection messages are in the files (as
many as its n_detections); every ok result has the six table_bc errors. Prints one line
"daemon recordings check of DIR: ok (N files, M messages)" or the problems; exits 1 on problems.

--partial mode reads a file the service was writing when it died, record by record with
`mcap.stream_reader.StreamReader`, until the first error (the cut), prints how many messages
were recoverable and exits 0 if there was at least one.
"""
import collections
import glob
import json
import os
import sys

from jsonschema import Draft202012Validator
from mcap.reader import make_reader
from mcap.records import Channel, Message
from mcap.stream_reader import StreamReader

CONTRACT = ["/machine/info", "/machine/state", "/spindle", "/temperature",
            "/probe/detection", "/cycle/result"]
ERRORS = {"EX0B", "EZ0B", "EY0C", "EX0C", "EA0C", "EB0C"}


def check_file(path, problems, topics, detections, results):
    """Check one closed file; add what it holds to topics, detections, results. Returns the
    number of messages read."""
    name = os.path.basename(path)
    n = 0
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        summary = reader.get_summary()
        if summary is None:
            problems.append(f"{name}: no summary (the file was not finished)")
            return 0
        for ch in summary.channels.values():
            topics.add(ch.topic)
            if ch.message_encoding != "json":
                problems.append(f"{name} {ch.topic}: message encoding {ch.message_encoding!r}")
            schema = summary.schemas.get(ch.schema_id)
            if schema is None:
                problems.append(f"{name} {ch.topic}: no schema")
            elif schema.encoding != "jsonschema":
                problems.append(f"{name} {ch.topic}: schema encoding {schema.encoding!r}")
            else:
                try:
                    kind = json.loads(schema.data).get("type")
                except (ValueError, AttributeError) as e:
                    kind = f"unreadable ({e})"
                if kind != "object":
                    problems.append(f"{name} {ch.topic}: schema type {kind!r}, not 'object'")
        last = {}
        out_of_order = collections.Counter()
        validators = {}
        invalid = collections.Counter()
        # File order, not log-time order: a reader that sorts would hide a writer going back.
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            n += 1
            topic = channel.topic
            if message.log_time < last.get(topic, 0):
                out_of_order[topic] += 1
            last[topic] = max(message.log_time, last.get(topic, 0))
            try:
                body = json.loads(message.data)
            except ValueError as e:
                problems.append(f"{name} {topic} at {message.log_time}: not JSON ({e})")
                continue
            if schema.id not in validators:
                validators[schema.id] = Draft202012Validator(json.loads(schema.data))
            if not validators[schema.id].is_valid(body):
                invalid[topic] += 1
            if topic == "/probe/detection":
                detections[body.get("cycle")] += 1
            elif topic == "/cycle/result":
                results.append((name, body))
        for topic, count in sorted(invalid.items()):
            problems.append(f"{name} {topic}: {count} messages break the channel's schema")
        for topic, count in sorted(out_of_order.items()):
            problems.append(f"{name} {topic}: log time goes back {count} times")
        counts = summary.statistics.channel_message_counts if summary.statistics else {}
        if summary.statistics is not None and sum(counts.values()) != n:
            problems.append(f"{name}: statistics say {sum(counts.values())} messages, read {n}")
    return n


def check_dir(d, short=False):
    files = sorted(glob.glob(os.path.join(d, "*.mcap")))
    problems = []
    if not files:
        problems.append("no .mcap file")
    topics = set()
    detections = collections.Counter()
    results = []
    messages = 0
    for path in files:
        try:
            messages += check_file(path, problems, topics, detections, results)
        except Exception as e:  # a reader error is a finding, not a crash of the check
            problems.append(f"{os.path.basename(path)}: cannot be read: {type(e).__name__}: {e}")
    if files and not short:
        for topic in CONTRACT:
            if topic not in topics:
                problems.append(f"no file has topic {topic}")
    seen = {}
    for name, r in results:
        cycle = r.get("cycle")
        if cycle in seen:
            problems.append(f"{name}: a second /cycle/result of cycle {cycle} (first in {seen[cycle]})")
            continue
        seen[cycle] = name
        want = r.get("n_detections")
        have = detections.get(cycle, 0)
        if have == 0:
            problems.append(f"{name}: cycle {cycle} has a result but no /probe/detection")
        elif isinstance(want, int) and have != want:
            problems.append(f"{name}: cycle {cycle}: result counts {want} detections, files hold {have}")
        if r.get("status") == "ok" and set(r.get("errors") or {}) != ERRORS:
            problems.append(f"{name}: ok cycle {cycle} has errors {sorted(r.get('errors') or {})}")
    for p in problems:
        print("FAIL", p)
    if problems:
        print(f"daemon recordings check of {d}: {len(problems)} problems")
        return 1
    print(f"daemon recordings check of {d}: ok ({len(files)} files, {messages} messages)")
    return 0


def check_partial(path):
    channels = {}
    counts = collections.Counter()
    stop = "the file ends cleanly"
    try:
        with open(path, "rb") as f:
            for record in StreamReader(f, validate_crcs=True).records:
                if isinstance(record, Channel):
                    channels[record.id] = record.topic
                elif isinstance(record, Message):
                    counts[channels.get(record.channel_id, f"channel {record.channel_id}")] += 1
    except Exception as e:  # the cut: whatever the reader trips on first
        stop = f"stopped at {type(e).__name__}: {e}"
    total = sum(counts.values())
    detail = ", ".join(f"{t} {n}" for t, n in sorted(counts.items()))
    print(f"partial recording {path}: {total} messages recoverable ({detail}); {stop}")
    return 0 if total > 0 else 1


def main(argv):
    if len(argv) == 3 and argv[1] == "--partial":
        return check_partial(argv[2])
    if len(argv) == 2 and not argv[1].startswith("-"):
        return check_dir(argv[1])
    if len(argv) == 3 and argv[1] == "--short":
        return check_dir(argv[2], short=True)
    print("usage: python3 check_daemon_files.py [--short] DIR\n"
          "       python3 check_daemon_files.py --partial FILE.mcap.partial", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv))
