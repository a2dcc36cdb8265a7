"""commands: control and parameter writes from a request to the bus and back.

`endpoints.py` (submit, list, cancel: roles and scopes checked there), `service.py`
(`CommandService`: refuses what cannot be sent, queues rows, delivers, repeats, confirms),
`repository.py` (the command queue's rows), `identify.py` (asks new units who they are).
"""
