"""The live 3D view in the browser (issue 11): :class:`~hrm_ctrl.view.server.ArmView`
serves the environment, the plan and the arm (planned, or as the host estimates it) on
127.0.0.1 with viser; :mod:`hrm_ctrl.view.geometry` is what it draws, as arrays, and
:mod:`hrm_ctrl.view.tip_camera` renders the tip camera's frames on the host.

Imports only the model, the kinematics, the planning environment and the plan format
(the layer of formats, planning and ropes in ``[tool.importlinter]``): the console
(``hrm_ctrl/cli/view.py``, ``hrm_ctrl/cli/_live.py``) feeds it drive feedback.
"""
