"""Read a driftwatch recording with the `mcap` Python package (an independent reader) and
check it against the recording contract: topics, encodings, schemas and message counts, and
every message against the JSON Schema its channel publishes (the `jsonschema` package).

usage: python3 check_recording.py FILE.mcap CYCLES STEPS_PER_CYCLE
"""
import json
import sys

from jsonschema import Draft202012Validator
from mcap.reader import make_reader

CONTRACT = ["/machine/info", "/machine/state", "/spindle", "/temperature",
            "/probe/detection", "/cycle/result"]


def main() -> int:
    path, cycles, steps = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
    failures = []
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        summary = reader.get_summary()
        counts = summary.statistics.channel_message_counts
        by_topic = {}
        for cid, ch in summary.channels.items():
            by_topic[ch.topic] = counts.get(cid, 0)
            schema = summary.schemas[ch.schema_id]
            if ch.message_encoding != "json":
                failures.append(f"{ch.topic}: message encoding {ch.message_encoding}")
            if schema.encoding != "jsonschema":
                failures.append(f"{ch.topic}: schema encoding {schema.encoding}")
            elif json.loads(schema.data).get("type") != "object":
                failures.append(f"{ch.topic}: schema is not an object schema")
        for topic in CONTRACT:
            if topic not in by_topic:
                failures.append(f"missing topic {topic}")
        if by_topic.get("/probe/detection") != cycles * steps:
            failures.append(f"/probe/detection: {by_topic.get('/probe/detection')} messages")
        if by_topic.get("/cycle/result") != cycles:
            failures.append(f"/cycle/result: {by_topic.get('/cycle/result')} messages")
        last = {}
        validators = {}
        invalid = {}
        for schema, channel, message in reader.iter_messages():
            body = json.loads(message.data)
            if schema.id not in validators:
                validators[schema.id] = Draft202012Validator(json.loads(schema.data))
            for e in validators[schema.id].iter_errors(body):
                invalid.setdefault(channel.topic, []).append(e.message)
            if message.log_time < last.get(channel.topic, 0):
                failures.append(f"{channel.topic}: log times out of order")
            last[channel.topic] = message.log_time
            if channel.topic == "/cycle/result" and body["status"] == "ok":
                if set(body["errors"]) != {"EX0B", "EZ0B", "EY0C", "EX0C", "EA0C", "EB0C"}:
                    failures.append(f"cycle {body['cycle']}: error names {sorted(body['errors'])}")
    for topic, errors in invalid.items():
        failures.append(f"{topic}: {len(errors)} schema violations, first: {errors[0]}")
    for f in failures:
        print("FAIL", f)
    verdict = "ok" if not failures else f"{len(failures)} problems"
    print(f"recording contract check of {path} with the mcap package: {verdict}")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
