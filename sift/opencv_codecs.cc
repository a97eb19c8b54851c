#include "sift/opencv_codecs.h"

#include <dlfcn.h>

#include <string_view>
#include <type_traits>

#include <opencv2/imgcodecs.hpp>

#ifndef OXBOW_OPENCV_IMGCODECS_SONAME
#error "OXBOW_OPENCV_IMGCODECS_SONAME (the soname of libopencv_imgcodecs) is set by sift/CMakeLists.txt"
#endif

namespace oxbow::sift::opencv_codecs {
namespace {

// The functions' C++ symbols in libopencv_imgcodecs (GCC's mangling, libstdc++'s std::string). The
// soname pins the ABI: OpenCV changes the soname with every release. The pointer types come from
// <opencv2/imgcodecs.hpp> through decltype, so a signature that changed would not compile.
constexpr std::string_view kImdecode = "_ZN2cv8imdecodeERKNS_11_InputArrayEi";
constexpr std::string_view kImencode =
    "_ZN2cv8imencodeERKNSt7__cxx1112basic_stringIcSt11char_traitsIcESaIcEEERKNS_11_InputArrayERSt6vectorIhSaIhEERKSB_"
    "IiSaIiEE";
constexpr std::string_view kImread = "_ZN2cv6imreadERKNSt7__cxx1112basic_stringIcSt11char_traitsIcESaIcEEEi";
constexpr std::string_view kImwrite =
    "_ZN2cv7imwriteERKNSt7__cxx1112basic_stringIcSt11char_traitsIcESaIcEEERKNS_11_InputArrayERKSt6vectorIiSaIiEE";

using ImdecodeFn = cv::Mat (*)(cv::InputArray, int);
using ImencodeFn = bool (*)(const cv::String&, cv::InputArray, std::vector<uchar>&, const std::vector<int>&);
using ImreadFn = cv::Mat (*)(const cv::String&, int);
using ImwriteFn = bool (*)(const cv::String&, cv::InputArray, const std::vector<int>&);
static_assert(std::is_same_v<ImdecodeFn, decltype(static_cast<cv::Mat (*)(cv::InputArray, int)>(&cv::imdecode))>);
static_assert(std::is_same_v<ImencodeFn, decltype(&cv::imencode)>);
static_assert(std::is_same_v<ImreadFn, decltype(&cv::imread)>);
static_assert(std::is_same_v<ImwriteFn, decltype(&cv::imwrite)>);

struct Library {
  ImdecodeFn imdecode = nullptr;
  ImencodeFn imencode = nullptr;
  ImreadFn imread = nullptr;
  ImwriteFn imwrite = nullptr;
  std::string error;  // why the library or a function could not be loaded; empty when all are
};

// Loads the library once per process; it stays loaded (no dlclose) as OpenCV keeps global state.
const Library& Load() {
  static const Library library = [] {
    Library l;
    void* handle = dlopen(OXBOW_OPENCV_IMGCODECS_SONAME, RTLD_NOW | RTLD_LOCAL);
    if (handle == nullptr) {
      const char* why = dlerror();
      l.error = std::string("OpenCV's image codecs (" OXBOW_OPENCV_IMGCODECS_SONAME ", Debian package libopencv-imgcodecs406) "
                            "cannot be loaded: ") + (why ? why : "unknown error");
      return l;
    }
    auto symbol = [&](std::string_view name) -> void* {
      void* address = dlsym(handle, std::string(name).c_str());
      if (address == nullptr && l.error.empty()) {
        l.error = "OpenCV's image codecs (" OXBOW_OPENCV_IMGCODECS_SONAME ") lack the function " + std::string(name);
      }
      return address;
    };
    l.imdecode = reinterpret_cast<ImdecodeFn>(symbol(kImdecode));
    l.imencode = reinterpret_cast<ImencodeFn>(symbol(kImencode));
    l.imread = reinterpret_cast<ImreadFn>(symbol(kImread));
    l.imwrite = reinterpret_cast<ImwriteFn>(symbol(kImwrite));
    return l;
  }();
  return library;
}

// Calls `call(library)` once the library is loaded; an exception OpenCV throws becomes `failure`.
template <typename Call>
auto Guarded(ErrorCode failure, Call&& call) -> Result<decltype(call(Load()))> {
  const Library& library = Load();
  if (!library.error.empty()) return Fail(ErrorCode::kUnsupportedFormat, library.error);
  try {
    return call(library);
  } catch (const cv::Exception& e) {
    return Fail(failure, e.what());
  }
}

}  // namespace

Result<cv::Mat> Decode(std::span<const uint8_t> bytes, int flags) {
  return Guarded(ErrorCode::kInvalidImage, [&](const Library& library) {
    const cv::Mat buffer(1, static_cast<int>(bytes.size()), CV_8U, const_cast<uint8_t*>(bytes.data()));
    return library.imdecode(buffer, flags);
  });
}

Result<bool> Encode(const std::string& extension, const cv::Mat& image, std::vector<uint8_t>& out,
                    const std::vector<int>& params) {
  return Guarded(ErrorCode::kIoError, [&](const Library& library) { return library.imencode(extension, image, out, params); });
}

Result<cv::Mat> Read(const std::string& path, int flags) {
  return Guarded(ErrorCode::kInvalidImage, [&](const Library& library) { return library.imread(path, flags); });
}

Result<bool> Write(const std::string& path, const cv::Mat& image, const std::vector<int>& params) {
  return Guarded(ErrorCode::kIoError, [&](const Library& library) { return library.imwrite(path, image, params); });
}

}  // namespace oxbow::sift::opencv_codecs
