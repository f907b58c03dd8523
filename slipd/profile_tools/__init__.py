"""The first tools a user runs on a new car: propose a profile from a DBC (scaffold), check a
profile on a real log without ground truth (check), and decode a log into slipd's SI input
channels (decode)."""
