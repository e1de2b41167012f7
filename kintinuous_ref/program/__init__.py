"""The program around the algorithms: the `kintinuous` command and what its commands drive.

    cli.py            the command line: the parser, one-line errors, signals; each command's
                      arguments in arguments.py, its body in commands.py, and --config / --set
                      in config_options.py
    reconstruct.py    a dataset in, a folder of results out (kintinuous_ref.pipeline.run inside)
    evaluation/       the paper's results section: runs of every method, tables, figures
    benchmark.py      per-stage milliseconds and frames/s on one backend

The dependency points one way, as in evo's core and cli: these modules use the algorithms
(kintinuous_ref's other modules), and no algorithm imports them (tests/test_architecture.py).
"""
