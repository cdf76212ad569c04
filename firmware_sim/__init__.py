# python-can without asammdf (and pandas), before the simulator or can_remote imports it: see
# mrrig/pycan.py
import mrrig.pycan  # noqa: F401
