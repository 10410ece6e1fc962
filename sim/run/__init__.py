"""Runs of a scenario: in the lockstep (``lockstep_case``) and on a bus (``fleet_plan``,
``busrun`` with its parts ``busopts``, ``nodeprocs``, ``recorder``; ``inprocess`` on a
simulated clock), with the recorder's log read back (``buslog``), the verdict, the report
(``runreport``), the analysis of a recorded log and the fleet's key sets (``keyset``)."""
