"""The supervisor: its builder, service, books and status files, policy, evidence and control."""
