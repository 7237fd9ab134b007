"""`--help` for the rospy nodes: the node's docstring and its private parameters, printed before
rospy starts (so no master is needed) and the process exits 0."""

import sys


def exit_if_help(doc, parameters=(), argv=None):
    """If argv (default sys.argv) asks for -h/--help: print `doc` and `parameters`
    ((name, meaning) pairs; defaults are in the package README) and exit 0."""
    argv = sys.argv[1:] if argv is None else argv
    if not {"-h", "--help"} & set(argv):
        return
    lines = [doc.strip()]
    if parameters:
        lines += ["", "Private parameters (_name:=value on the command line, <param> in launch files):"]
        lines += [f"  ~{name}: {meaning}" for name, meaning in parameters]
    lines += ["", "Remap topics as usual (name:=new_name); __ns:= and __name:= place the node."]
    print("\n".join(lines))
    raise SystemExit(0)
