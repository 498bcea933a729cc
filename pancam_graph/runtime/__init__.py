"""What a run needs of the machine: worker processes and their fork server, memory, numbers kept
in files for the whole traverse, scratch folders, atomic writes and text files read with one
clear error."""
