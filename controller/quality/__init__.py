"""The quality log: record schema, SQLite and PostgreSQL stores, the durable journal, the report."""
