"""The ``bbcity`` commands, one module each: its parser (``add(subparsers)``), the translation
of its options into the configs the stages take, and its run function (set as the parser's
``func`` default; it returns the exit code).

A command's parser may also set these defaults, which :mod:`bbcity.lifecycle` reads:
``check_options`` (a function of the parsed options raising :class:`~core.errors.InputError`
for a bad combination: a usage line before the command starts), ``writes_file`` (True, or a
function of ``--out``: the command writes one file there, not a directory) and
``own_output`` (a :class:`~bbcity.commands.common.OwnOutput`: what the command's directory may
hold from an earlier run of it). Options and checks several commands share are in
:mod:`.common`; the bounds of the values, in :mod:`bbcity.options`.
"""
