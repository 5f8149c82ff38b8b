"""Prefect flows that wire the tasks into DAGs (mesh_library, retry_failed, scan_drops, train). Populated by the orchestration issue."""
