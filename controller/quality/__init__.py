"""The quality log.

Record schema, SQLite and PostgreSQL stores, the durable journal, the report.
"""
