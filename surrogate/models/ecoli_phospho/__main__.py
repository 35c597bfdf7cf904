"""``python -m surrogate.models.ecoli_phospho``: write ``network.xml`` and
``network_amounts.xml`` from the default constants."""

from surrogate.models.ecoli_phospho.sbml_writer import main

if __name__ == "__main__":
    main()
