"""Files that survive kills and concurrent writers: file locks and append-only JSON logs."""
