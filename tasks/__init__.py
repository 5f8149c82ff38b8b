"""Thin Prefect tasks, one per pipeline stage (each calls one library function). Populated by the orchestration issue."""
