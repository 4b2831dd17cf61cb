"""The flight report (``cmnav report``): an HTML page and a PNG drawn from one flight log.
Drawing needs the optional extra ``report`` (matplotlib); reading the log does not."""

from .flight_data import FlightData, read_flight
from .render import ReportUnavailableError, find_companions, report_paths, write_report, write_report_quietly

__all__ = ["FlightData", "ReportUnavailableError", "find_companions", "read_flight", "report_paths", "write_report",
           "write_report_quietly"]
