"""The fit's pictures: the fitted model on its records (fitted) and the six panels
drawn with matplotlib (figures, the optional extra hamid[plot])."""
