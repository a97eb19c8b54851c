#include "server/cli/modules/module_loader.h"

#include <dlfcn.h>

#include <cstdlib>
#include <filesystem>
#include <map>
#include <mutex>
#include <system_error>

namespace oxbow::cli {
namespace {

namespace fs = std::filesystem;

fs::path ModuleDir() {
  if (const char* dir = std::getenv("OXBOW_MODULE_DIR"); dir != nullptr && *dir != '\0') return dir;
  std::error_code error;
  const fs::path binary = fs::read_symlink("/proc/self/exe", error);
  if (error) return "/usr/lib/oxbow";
  return binary.parent_path().parent_path() / "lib" / "oxbow";
}

}  // namespace

Result<void*> LoadModuleEntry(const std::string& name, const char* entry) {
  static std::mutex mutex;
  static std::map<std::string, void*> handles;  // loaded modules stay loaded for the life of the process
  std::lock_guard lock(mutex);
  void*& handle = handles[name];
  const fs::path path = ModuleDir() / ("lib" + name + ".so");
  if (handle == nullptr) {
    if (!fs::exists(path)) {
      return Fail(ErrorCode::kNotFound, "the oxbow module " + path.string() + " is missing (it is built and installed with the "
                                        "binary; OXBOW_MODULE_DIR names another folder)");
    }
    // RTLD_GLOBAL: Open MPI's own plugins look up libmpi's symbols in the global scope.
    handle = dlopen(path.c_str(), RTLD_NOW | RTLD_GLOBAL);
    if (handle == nullptr) {
      const char* why = dlerror();
      return Fail(ErrorCode::kIncompatible, "cannot load the oxbow module " + path.string() + ": " + (why ? why : "unknown error"));
    }
  }
  dlerror();
  void* address = dlsym(handle, entry);
  if (address == nullptr) {
    return Fail(ErrorCode::kIncompatible, "the oxbow module " + path.string() + " has no function " + entry +
                                              " (a module of another oxbow version?)");
  }
  return address;
}

}  // namespace oxbow::cli
