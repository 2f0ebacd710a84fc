"""The links of guarded devices other than CiA 402 drives (ODrive, moteus), and MIT-mode motors
in line."""
