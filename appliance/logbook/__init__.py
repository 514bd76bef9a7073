"""The logbook: one MCAP file per session, readable in Foxglove, durable across power cuts.

- :mod:`appliance.logbook.topics`: topic names, schema names and the JSON schemas of raw records.
- :mod:`appliance.logbook.messages`: pure builders of the Foxglove protobuf messages.
- :mod:`appliance.logbook.sink`: the write-through, fsync-able file under the MCAP writer.
- :mod:`appliance.logbook.writer`: :class:`Logbook`, the session writer (flush + fsync, full disk).
- :mod:`appliance.logbook.reader`: reading a log, complete or truncated, with an error policy.
- :mod:`appliance.logbook.recover`: rewriting a truncated log into a valid one.
- :mod:`appliance.logbook.summary`: what ``viper log info`` prints.
- :mod:`appliance.logbook.live`: the live view (Foxglove WebSocket), with its channels
  (:mod:`appliance.logbook.live_channels`) and its drain at close (:mod:`appliance.logbook.live_drain`).
"""

from appliance.errors import ErrorPolicy
from appliance.logbook.reader import LogMessage, LogReader
from appliance.logbook.recover import RecoveryReport, recover_log
from appliance.logbook.writer import Logbook, LogbookFullError

__all__ = [
    "ErrorPolicy",
    "LogMessage",
    "LogReader",
    "Logbook",
    "LogbookFullError",
    "RecoveryReport",
    "recover_log",
]
