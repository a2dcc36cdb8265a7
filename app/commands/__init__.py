"""commands: control and parameter writes from a request to the bus and back.

`endpoints.py` (submit, list, cancel: roles and scopes checked there), `service.py`
(`CommandService`: what a command reaches, refusals, queueing rows), `validation.py` (the
payload checks, conflicts, idempotent replays), `delivery.py` (the loop that hands frames to
the bus, repeats and ends commands), `lifecycle.py` (pure: every decision of a command's life
from the facts), `model.py` (`Command`, its kinds and states, the API view), `schemas.py` (the
routes' bodies and their answer, `CommandOut`), `repository.py` (the command queue's rows),
`identify.py` (asks new units who they are).
"""
