"""Validates a Croissant document with MLCommons' mlcroissant and reads records through it.

Usage: croissant_check.py DOCUMENT N
Prints one JSON line: the issues mlcroissant found (errors and warnings) and the first N records of the
`transitions` record set as mlcroissant reads them from the document's Parquet file (over HTTP, checking its sha256).
"""
import json
import sys

import mlcroissant as mlc


def main(path, n):
    dataset = mlc.Dataset(jsonld=path)
    issues = dataset.metadata.ctx.issues
    records = []
    for i, record in enumerate(dataset.records(record_set="transitions")):
        if i >= n:
            break
        records.append({key.split("/")[-1]: _plain(value) for key, value in record.items()})
    print(json.dumps({"errors": sorted(issues.errors), "warnings": sorted(issues.warnings), "records": records}))


def _plain(value):
    if hasattr(value, "tolist"):
        return value.tolist()
    if isinstance(value, bytes):
        return value.decode()
    return value


if __name__ == "__main__":
    main(sys.argv[1], int(sys.argv[2]))
