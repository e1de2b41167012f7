"""Loop closure with map deformation (Whelan et al., IROS 2013; Kintinuous, IJRR 2015)."""
