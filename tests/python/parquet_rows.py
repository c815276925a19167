"""Prints the first N rows of a Parquet file as pyarrow reads them, as one JSON line (lists for list columns)."""
import json
import sys

import pyarrow.parquet as pq

table = pq.read_table(sys.argv[1]).slice(0, int(sys.argv[2]))
print(json.dumps(table.to_pylist()))
