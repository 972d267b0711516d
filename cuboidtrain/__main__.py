from cuboidtrain.cli import main

main()
