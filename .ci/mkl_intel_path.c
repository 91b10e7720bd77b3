/* Preloaded into one run of the quick suite on a CPU that is not Intel's (.ci/run): MKL asks this
   function whether the CPU is Intel's and takes its Intel-only kernels (other blockings and
   summation orders in BLAS and LAPACK) when it answers 1.  torch exports MKL's symbols and calls
   this one through its PLT, so the preloaded definition is the one called. */
int mkl_serv_intel_cpu_true(void) { return 1; }
