"""`python -m cuboidtrain`: the same command line as `cuboidtrain`."""
from cuboidtrain.cli import main

main()
