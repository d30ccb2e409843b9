"""Hardware-in-the-loop runs: the service closed around the simulated planer (``planer hil``).

Two ways to run the same scenario:

* **cross-process** (default when possible): ``planer hil`` re-executes itself inside a private
  network namespace (``unshare -rn``: loopback only, multicast routed on ``lo``), starts
  ``planer sim`` there as a separate process (Modbus TCP on 127.0.0.1, CAN over python-can's
  ``udp_multicast``, frames through a spool directory) and runs the real-time service against
  it (:func:`run_cross_process`).
* **in-process** (fallback, tests): the :class:`plant_sim.machine.machine.Machine` and the
  service in one process on *simulated time*, stepped in lockstep every control cycle: the PLC
  through :class:`~plant_sim.interfaces.register_bus.MachineRegisterBus` (or the real Modbus
  server on an ephemeral loopback port), the amplifier node on python-can's ``virtual`` bus
  (:class:`InProcessHil`).

Both end with :func:`summarize`: per measurement the measured and the simulator's true pitch and
uniformity (``Frame.truth``) and the setpoints; ``initial`` and ``final`` true values; where the
true values settled (board travel after the loop closed); whether every setpoint stayed inside
the machine's limits; what each injected fault did (safe state, recovery); the quality log's
integrity.

The package, by job: :mod:`planer.hil.scenario` (what to run), :mod:`planer.hil.in_process`
(simulated time, one process; :mod:`planer.hil.pacing` holds it to the wall clock when asked),
:mod:`planer.hil.cross_process` (real time, two processes),
:mod:`planer.hil.summary` (what the run achieved; :func:`json_ready` for strict JSON),
:mod:`planer.hil.run_end` (the distance run, or the limit that cut the run: a check),
:mod:`planer.hil.soak` (an hour of machine time with faults: memory, files and latency flat;
``python -m planer.hil.soak``). Fault kinds and their parameters: :mod:`config.faults`.
"""

from planer.hil.cross_process import cross_process_possible, run_cross_process, to_toml
from planer.hil.in_process import InProcessHil, InProcessPlant
from planer.hil.scenario import (
    FaultEvent,
    Scenario,
    load_scenario,
    machine_config_for,
    scenario_from_table,
    sim_config_for,
    sim_document,
)
from planer.hil.summary import BoardTravel, check_log, json_ready, safe_periods, summarize

__all__ = [
    "BoardTravel",
    "FaultEvent",
    "InProcessHil",
    "InProcessPlant",
    "Scenario",
    "check_log",
    "cross_process_possible",
    "json_ready",
    "load_scenario",
    "machine_config_for",
    "run_cross_process",
    "safe_periods",
    "scenario_from_table",
    "sim_config_for",
    "sim_document",
    "summarize",
    "to_toml",
]
