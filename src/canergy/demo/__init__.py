"""``canergy demo``: a supervisor and several clients on python-can's virtual bus, under faults."""

from canergy.demo.config import DemoConfig
from canergy.demo.report import format_report
from canergy.demo.result import DemoResult, NodeStats
from canergy.demo.run import run_demo

__all__ = ["DemoConfig", "DemoResult", "NodeStats", "format_report", "run_demo"]
