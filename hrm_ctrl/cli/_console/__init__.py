"""The operator console (``hrm console``, ``hrm status``): one command table over one live
drive session.

:mod:`.table` holds the commands (:data:`~.table.COMMANDS`, the :func:`~.table.command`
decorator), :mod:`.context` what they work on (:class:`~.context.ConsoleContext`), the
``commands_*`` modules register the commands, :mod:`.shell` runs them interactively
(prompt_toolkit) or line by line from a script.  Not a command itself (its name starts
with ``_``).
"""
