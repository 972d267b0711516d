"""The page (`cuboidtrain serve`): a local web app to try the shipped models on a mask, see the fit
and its explanation, and turn the box in 3D. It fits through `infer`'s own path (`answer`), in a
pool of worker processes (`server`), and serves every script it needs itself (`app`)."""
