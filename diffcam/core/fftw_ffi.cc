// XLA FFI handlers that run diffcam's 2-D FFTs with FFTW (diffcam.core.fftw).
//
// FFTW is not linked: Python loads its shared libraries (pyFFTW's wheel ships them,
// or the system's) and hands the addresses of the functions below to
// diffcam_fftw_bind. Each handler transforms the last two axes of a row-major
// buffer, batched over the leading ones, unnormalised (FFTW's conventions; the
// 1/(ny*nx) of an inverse transform is applied in JAX, where XLA fuses it).
//
// Plans are made once per (precision, kind, shape, alignment, in place, threads,
// effort) under a lock, on a scratch input and the caller's output (measuring writes
// to both; the scratch alone when in place), and executed on each transform of a batch
// in turn with the new-array functions, which FFTW documents as thread-safe. Complex
// transforms run in place (XLA aliases their output to their input). A c2r transform overwrites its input, so it runs on
// a copy: XLA's operand buffers are not ours to change. FFTW's wisdom (what its
// measurements found) is exported and imported as strings for Python to keep.

#include <condition_variable>
#include <cstdint>
#include <cstring>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <tuple>

#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;

namespace {

using Plan = void*;

// FFTW's documented C API (fftw3.h), one table per precision; complex and real
// arrays are passed as untyped pointers, which is ABI-compatible.
struct Api {
  Plan (*plan_many_dft)(int, const int*, int, void*, const int*, int, int, void*,
                        const int*, int, int, int, unsigned);
  Plan (*plan_many_dft_r2c)(int, const int*, int, void*, const int*, int, int, void*,
                            const int*, int, int, unsigned);
  Plan (*plan_many_dft_c2r)(int, const int*, int, void*, const int*, int, int, void*,
                            const int*, int, int, unsigned);
  void (*execute_dft)(Plan, void*, void*);
  void (*execute_dft_r2c)(Plan, void*, void*);
  void (*execute_dft_c2r)(Plan, void*, void*);
  void (*destroy_plan)(Plan);
  void (*plan_with_nthreads)(int);
  int (*alignment_of)(void*);
  void* (*malloc)(size_t);
  void (*free)(void*);
  void (*set_timelimit)(double);
  char* (*export_wisdom_to_string)(void);
  int (*import_wisdom_from_string)(const char*);
};

constexpr unsigned kMeasure = 0u;          // FFTW_MEASURE
constexpr unsigned kUnaligned = 1u << 1;   // FFTW_UNALIGNED
constexpr unsigned kDestroyInput = 1u;     // FFTW_DESTROY_INPUT

enum Kind { kForward = 0, kBackward = 1, kR2C = 2, kC2R = 3 };

Api apis[2];            // [0] single, [1] double precision
bool bound[2] = {false, false};
int threads = 1;
unsigned effort = kMeasure;
double timelimit = -1;  // seconds per plan (FFTW_NO_TIMELIMIT)
std::mutex planner;     // FFTW's planner is not thread-safe
int64_t plans_made = 0;
std::map<std::tuple<int, int, int64_t, int64_t, bool, bool, int, unsigned>, Plan> plans;

struct Scratch {  // grows to the largest c2r input seen by this thread
  int precision = 0;
  void* data = nullptr;
  size_t bytes = 0;
  ~Scratch() {
    if (data != nullptr) apis[precision].free(data);
  }
};
thread_local Scratch scratch[2];

// One thread runs every transform: FFTW's OpenMP threads then stay one warm team.
// Called from whichever of XLA's threads runs the custom call, FFTW started a team per
// calling thread, and a pair of transforms measured 4-5x one transform.
class FftThread {
 public:
  static FftThread& Get() {
    static FftThread* one = new FftThread();  // never destroyed: its thread is detached
    return *one;
  }
  void Run(const std::function<void()>& work) {
    std::lock_guard<std::mutex> turn(submit_);
    std::unique_lock<std::mutex> lock(m_);
    work_ = &work;
    cv_.notify_all();
    cv_.wait(lock, [this] { return work_ == nullptr; });
  }

 private:
  FftThread() { std::thread([this] { Loop(); }).detach(); }
  void Loop() {
    std::unique_lock<std::mutex> lock(m_);
    for (;;) {
      cv_.wait(lock, [this] { return work_ != nullptr; });
      (*work_)();
      work_ = nullptr;
      cv_.notify_all();
    }
  }
  std::mutex submit_, m_;
  std::condition_variable cv_;
  const std::function<void()>* work_ = nullptr;
};

size_t ComplexBytes(int precision) { return precision == 0 ? 8 : 16; }

// The plan for one transform of ny x nx (the real shape for r2c/c2r), made on a
// scratch input (planning writes to its arrays) and the caller's output.
Plan GetPlan(int precision, Kind kind, int64_t ny, int64_t nx, bool aligned, bool in_place,
             void* out) {
  std::lock_guard<std::mutex> lock(planner);
  auto key = std::make_tuple(precision, int(kind), ny, nx, aligned, in_place, threads, effort);
  auto found = plans.find(key);
  if (found != plans.end()) return found->second;
  ++plans_made;
  const Api& api = apis[precision];
  const int n[2] = {int(ny), int(nx)};
  const size_t cbytes = ComplexBytes(precision), rbytes = cbytes / 2;
  const int64_t full = ny * nx, spectrum = ny * (nx / 2 + 1);
  size_t in_bytes = kind == kR2C ? full * rbytes : (kind == kC2R ? spectrum : full) * cbytes;
  // an unaligned input is planned for at an offset of one element into the scratch
  size_t offset = aligned ? 0 : (kind == kR2C ? rbytes : cbytes);
  char* scratch_in = static_cast<char*>(api.malloc(in_bytes + offset));
  if (scratch_in == nullptr) return nullptr;
  std::memset(scratch_in, 0, in_bytes + offset);
  void* in = scratch_in + offset;
  if (in_place) out = in;  // the caller's output is its input: plan on the scratch
  unsigned flags = effort | (aligned ? 0u : kUnaligned);
  api.plan_with_nthreads(threads);
  api.set_timelimit(timelimit);
  Plan plan = nullptr;
  if (kind == kR2C) {
    plan = api.plan_many_dft_r2c(2, n, 1, in, nullptr, 1, 0, out, nullptr, 1, 0, flags);
  } else if (kind == kC2R) {
    plan = api.plan_many_dft_c2r(2, n, 1, in, nullptr, 1, 0, out, nullptr, 1, 0,
                                 flags | kDestroyInput);
  } else {
    plan = api.plan_many_dft(2, n, 1, in, nullptr, 1, 0, out, nullptr, 1, 0,
                             kind == kForward ? -1 : 1, flags);
  }
  api.free(scratch_in);
  if (plan != nullptr) plans[key] = plan;
  return plan;
}

int Precision(ffi::DataType type) {
  switch (type) {
    case ffi::DataType::F32:
    case ffi::DataType::C64:
      return 0;
    case ffi::DataType::F64:
    case ffi::DataType::C128:
      return 1;
    default:
      return -1;
  }
}

// Batch size and the last two dimensions of a buffer of rank >= 2.
bool Shape(const ffi::AnyBuffer& buffer, int64_t* howmany, int64_t* ny, int64_t* nx) {
  auto dims = buffer.dimensions();
  if (dims.size() < 2) return false;
  *howmany = 1;
  for (size_t i = 0; i + 2 < dims.size(); ++i) *howmany *= dims[i];
  *ny = dims[dims.size() - 2];
  *nx = dims[dims.size() - 1];
  return true;
}

// This thread's copy buffer for c2r inputs, at least `bytes` long (null if out of memory).
void* ScratchFor(int precision, size_t bytes) {
  Scratch& s = scratch[precision];
  if (s.bytes < bytes) {
    if (s.data != nullptr) apis[precision].free(s.data);
    s.precision = precision;
    s.data = apis[precision].malloc(bytes);
    s.bytes = s.data == nullptr ? 0 : bytes;
  }
  return s.data;
}

ffi::Error Transform(Kind kind, ffi::AnyBuffer x, ffi::Result<ffi::AnyBuffer> y) {
  int precision = Precision(x.element_type());
  if (precision < 0 || !bound[precision]) {
    return ffi::Error::InvalidArgument("diffcam FFTW: unsupported dtype or precision not bound");
  }
  int64_t howmany, ny, nx;
  // the real shape: the input's for r2c, the output's for c2r
  const ffi::AnyBuffer& real_side = kind == kC2R ? *y : x;
  if (!Shape(real_side, &howmany, &ny, &nx)) {
    return ffi::Error::InvalidArgument("diffcam FFTW: arrays need two dimensions");
  }
  if (howmany == 0 || ny == 0 || nx == 0) return ffi::Error::Success();
  if (ny * nx > INT32_MAX) {
    return ffi::Error::InvalidArgument("diffcam FFTW: more than 2^31 - 1 samples per transform");
  }
  const Api& api = apis[precision];
  const size_t cbytes = ComplexBytes(precision), rbytes = cbytes / 2;
  const int64_t full = ny * nx, spectrum = ny * (nx / 2 + 1);
  const size_t in_step = kind == kR2C ? full * rbytes : (kind == kC2R ? spectrum : full) * cbytes;
  const size_t out_step = kind == kC2R ? full * rbytes : (kind == kR2C ? spectrum : full) * cbytes;
  void* copy = kind == kC2R ? ScratchFor(precision, in_step) : nullptr;
  if (kind == kC2R && copy == nullptr) return ffi::Error::Internal("diffcam FFTW: out of memory");
  // one plan per shape, executed on each transform of the batch in turn (each one
  // multi-threaded; a batched plan would need scratch arrays the size of the batch)
  char* in_at = static_cast<char*>(x.untyped_data());
  char* out_at = static_cast<char*>(y->untyped_data());
  for (int64_t b = 0; b < howmany; ++b, in_at += in_step, out_at += out_step) {
    void* in = in_at;
    if (kind == kC2R) {  // FFTW overwrites a multi-dimensional c2r input: use a copy
      std::memcpy(copy, in_at, in_step);
      in = copy;
    }
    bool aligned = api.alignment_of(in) == 0 && api.alignment_of(out_at) == 0;
    Plan plan = GetPlan(precision, kind, ny, nx, aligned, in == out_at, out_at);
    if (plan == nullptr) {
      return ffi::Error::Internal("diffcam FFTW: no plan for " + std::to_string(ny) + " x " +
                                  std::to_string(nx));
    }
    if (kind == kR2C) {
      api.execute_dft_r2c(plan, in, out_at);
    } else if (kind == kC2R) {
      api.execute_dft_c2r(plan, in, out_at);
    } else {
      api.execute_dft(plan, in, out_at);
    }
  }
  return ffi::Error::Success();
}

ffi::Error OnFftThread(Kind kind, ffi::AnyBuffer x, ffi::Result<ffi::AnyBuffer> y) {
  ffi::Error error = ffi::Error::Success();
  FftThread::Get().Run([&] { error = Transform(kind, x, y); });
  return error;
}

ffi::Error C2C(ffi::AnyBuffer x, ffi::Result<ffi::AnyBuffer> y, int64_t sign) {
  return OnFftThread(sign < 0 ? kForward : kBackward, x, y);
}
ffi::Error R2C(ffi::AnyBuffer x, ffi::Result<ffi::AnyBuffer> y) { return OnFftThread(kR2C, x, y); }
ffi::Error C2R(ffi::AnyBuffer x, ffi::Result<ffi::AnyBuffer> y) { return OnFftThread(kC2R, x, y); }

}  // namespace

XLA_FFI_DEFINE_HANDLER_SYMBOL(DiffcamFftwC2C, C2C,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::AnyBuffer>()
                                  .Ret<ffi::AnyBuffer>()
                                  .Attr<int64_t>("sign"));
XLA_FFI_DEFINE_HANDLER_SYMBOL(DiffcamFftwR2C, R2C,
                              ffi::Ffi::Bind().Arg<ffi::AnyBuffer>().Ret<ffi::AnyBuffer>());
XLA_FFI_DEFINE_HANDLER_SYMBOL(DiffcamFftwC2R, C2R,
                              ffi::Ffi::Bind().Arg<ffi::AnyBuffer>().Ret<ffi::AnyBuffer>());

extern "C" {

// table: the functions of struct Api, in its order, of one precision (0 single, 1 double).
int diffcam_fftw_bind(int precision, void** table) {
  if (precision < 0 || precision > 1) return 1;
  std::lock_guard<std::mutex> lock(planner);
  std::memcpy(&apis[precision], table, sizeof(Api));
  bound[precision] = true;
  return 0;
}

// How many plans have been made (each shape and setting once).
int64_t diffcam_fftw_plans_made() {
  std::lock_guard<std::mutex> lock(planner);
  return plans_made;
}

// Stands in for fftw_plan_with_nthreads when FFTW has no threads library.
void diffcam_fftw_no_threads(int) {}

// Threads, planning effort (FFTW flags) and planning time limit (seconds, < 0: none)
// of plans made from now on.
void diffcam_fftw_configure(int nthreads, unsigned planning_flags, double seconds) {
  std::lock_guard<std::mutex> lock(planner);
  threads = nthreads < 1 ? 1 : nthreads;
  effort = planning_flags;
  timelimit = seconds;
}

// FFTW's accumulated wisdom of one precision as a string (free with free()), or null.
char* diffcam_fftw_export_wisdom(int precision) {
  std::lock_guard<std::mutex> lock(planner);
  if (precision < 0 || precision > 1 || !bound[precision]) return nullptr;
  return apis[precision].export_wisdom_to_string();
}

// Adds wisdom (from diffcam_fftw_export_wisdom); returns FFTW's success flag.
int diffcam_fftw_import_wisdom(int precision, const char* wisdom) {
  std::lock_guard<std::mutex> lock(planner);
  if (precision < 0 || precision > 1 || !bound[precision]) return 0;
  return apis[precision].import_wisdom_from_string(wisdom);
}

}  // extern "C"
